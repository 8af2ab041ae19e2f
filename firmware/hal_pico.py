# HAL for the Raspberry Pi Pico (RP2040): potentiometer on an ADC pin, quadrature
# encoder decoded by a PIO state machine (no CPU per edge), PWM + DIR H-bridge.
# The only kind of module that imports machine; pins come from firmware/board.py.
#
# The driver enable (EN) is driven by a second PIO state machine, a dead-man (_deadman below):
# it holds EN low unless the control loop refreshes it every tick, so a hang anywhere (the
# step, the link, a HAL call, a C call that never returns, interrupts off) cuts the driver
# DEADMAN_PCT % of a loop period after the last refresh, whatever the CPU does
# (docs/firmware.md, "Hardware cut-offs").
#
# The PIO program is the pico-examples quadrature decoder (x4 decoding with a 16-entry
# jump table on the previous/current A,B state): the count lives in the Y register
# and its low 16 bits are pushed (noblock) on every change, so the CPU reads the
# latest value of a 16-bit counter -- exactly the wrapping counter the firmware
# expects (a push never exceeds 65535: no big ints).  The program fills all 32
# instruction slots, so it is loaded at offset 0 as its `mov(pc, isr)` jump table needs.

import machine
import rp2
import sys
import time
from array import array

from .hal_base import Hal

try:
    import micropython
    from micropython import const
except ImportError:  # CPython with stand-in machine/rp2 (tests): the viper paths stay unused
    class micropython:
        @staticmethod
        def viper(f):
            return f

    def const(x):
        return x

_PADS_BANK0 = const(0x4001C000)
_PUE = const(8)  # pad pull-up enable
_PDE = const(4)  # pad pull-down enable
# hardware watchdog: the reset-cause marker lives in WATCHDOG SCRATCH3, which a watchdog
# reset keeps (POR, brown-out and the RUN pin clear it; pico-sdk/bootrom use SCRATCH4-7)
_WD_SCRATCH3 = const(0x40058018)
_WD_CTRL_CLR = const(0x40058000 + 0x3000)  # CTRL atomic-clear alias
_WD_ENABLE = const(0x40000000)
_MARK = const(0x2AFE0000)  # marker | cause (a small int)
# PWM INTR (raw wrap flags, write 1 to clear): a new compare is in force after the next wrap
_PWM_INTR = const(0x400500A4)
_UART_BASE = (0x40034000, 0x40038000)  # UART0, UART1
_UARTIFLS = const(0x34)  # interrupt FIFO level select
_RX_HALF = const(2)  # RXIFLSEL: receive FIFO >= 1/2 full (16 of 32 bytes)
_WRAP_SPINS = const(400)  # bound of the wait for a wrap (one PWM period is a few spins)
# the per-tick I/O on the RP2040's registers (viper, installed by __init__ on the rp2 port
# only: the methods of the same names below are the portable reference).  One call each
# instead of a Python call per machine.ADC/PIO/PWM access: a call costs ~5-10 us on a
# 125 MHz M0+, the register access well under one.  _io holds their small-int state:
_IO_OS_N = const(0)  # ADC samples per reading
_IO_OS_K = const(1)  # ... their log2
_IO_OPEN_EVERY = const(2)  # open-wiper test period (readings; 0: off)
_IO_OPEN_N = const(3)  # readings since the last test
_IO_DIR = const(4)  # DIR level in force (== _dir_now)
_IO_MSIGN = const(5)  # motor sign
_IO_ADC_CH = const(6)  # ADC input of the angle pot (ADC_PIN - 26)
_IO_VSUP_CH = const(7)  # ADC input of the supply divider
_IO_VSUP_MUL = const(8)  # supply scale (see _read_supply_mv)
_IO_SM = const(9)  # encoder state machine within its PIO block
_IO_PIO = const(10)  # its PIO block (0, 1)
_IO_SLICE = const(11)  # PWM slice of the motor pin
_IO_CHAN = const(12)  # its channel (0: A, 1: B)
_IO_ESTOP = const(13)  # e-stop GPIO (-1: none)
_IO_DM_ON = const(14)  # dead-man: 1 while the driver is enabled (set_motor refreshes it)
_IO_DM_N = const(15)  # ... the refresh word: the count of _DM_LOOP_US loops EN stays high
_IO_DM_SM = const(16)  # ... its state machine within PIO1 (-1: no dead-man, EN a plain pin)
_IO_DM_TRIPS = const(17)  # ... expiries seen by the refresh (the loop came back too late)
_IO_N = const(18)
_SPINS = const(2000)  # bound of the waits for an ADC conversion (~2 us) or a PIO push
# dead-man timing: the state machine runs at 1 MHz (clock divider 125 at 125 MHz) and checks
# for a refresh once per 16-cycle loop; the count N in a refresh word keeps EN high for
# (N + 1) loops.  Without a loop period (no App yet: the REPL, the bench) the count is the
# largest small int (4.7 hours): EN then follows set_enable alone
_DM_HZ = const(1000000)
_DM_LOOP_US = const(16)
_DM_FOREVER = const(0x3FFFFFFF)
_PIO1_EXECCTRL = const(0x503000CC)  # SM0_EXECCTRL of PIO1 (+ 0x18 per machine)


@rp2.asm_pio(in_shiftdir=rp2.PIO.SHIFT_LEFT, out_shiftdir=rp2.PIO.SHIFT_RIGHT)
def _quadrature():
    # 00 state
    jmp("update")       # read 00
    jmp("decrement")    # read 01
    jmp("increment")    # read 10
    jmp("update")       # read 11
    # 01 state
    jmp("increment")    # read 00
    jmp("update")       # read 01
    jmp("update")       # read 10
    jmp("decrement")    # read 11
    # 10 state
    jmp("decrement")    # read 00
    jmp("update")       # read 01
    jmp("update")       # read 10
    jmp("increment")    # read 11
    # 11 state
    jmp("update")       # read 00
    jmp("increment")    # read 01
    label("decrement")
    jmp(y_dec, "update")  # read 10
    wrap_target()
    label("update")     # read 11
    mov(isr, null)
    in_(y, 16)
    push(noblock)
    label("sample_pins")
    out(isr, 2)
    in_(pins, 2)
    mov(osr, isr)
    mov(pc, isr)
    label("increment")
    mov(y, invert(y))
    jmp(y_dec, "increment_cont")
    label("increment_cont")
    mov(y, invert(y))
    wrap()
    # padding: 25 instructions above + 7 = 32 (the only possible load offset is then 0)
    nop()
    nop()
    nop()
    nop()
    nop()
    nop()
    nop()


@rp2.asm_pio(set_init=2)  # 2: rp2.PIO.OUT_LOW (a literal: the CPython stand-ins have no PIO.OUT_LOW)
def _deadman():
    # EN on the set pin.  A refresh word N > 0 sets EN high and (re)starts a count of N + 1
    # loops of 16 cycles; 0 sets it low at once.  The count running out sets EN low and raises
    # IRQ flag (rel 0) for the CPU to see.  `mov x, status` is all ones while the TX FIFO is
    # empty (EXECCTRL STATUS_SEL = TX, STATUS_N = 1: set by HalPico after the machine is made)
    label("off")
    set(pins, 0)
    label("idle")
    pull(block)
    mov(y, osr)
    jmp(not_y, "off")
    set(pins, 1)
    label("count")
    mov(x, status)[7]
    jmp(not_x, "idle")        # a word waits: take it
    jmp(y_dec, "count")[6]
    irq(rel(0))                 # expired: flag it; wraps to "off"


class HalPico(Hal):
    def __init__(self, board):
        self.b = board
        self._adc = machine.ADC(machine.Pin(board.ADC_PIN))
        self._adc_shift = board.ADC_SHIFT
        # oversampling: n samples summed, shifted back to 12-bit counts.  Floor, no rounding
        # constant: read_u16() is the 12-bit count v as (v << 4) | (v >> 8) (top bits repeated
        # in the low nibble), so n samples of v sum to (v << (4+k)) + n*(v >> 8) with
        # n*(v >> 8) < n*16 = 1 << (4+k): the floor shift gives v exactly; adding half an LSB
        # would read v+1 for every v >= 2048 (2048 -> 2049, 4095 -> 4096)
        n = getattr(board, "ADC_OVERSAMPLE", 1)
        k = 0
        while (1 << k) < n:
            k += 1
        self._os_n = 1 << k
        self._os_shift = board.ADC_SHIFT + k
        # open-wiper test (see read_angle_raw): PADS_BANK0 GPIOn register, its atomic
        # set/clear aliases (addresses made once: they are not small ints)
        self._open_every = getattr(board, "ADC_OPEN_TEST_TICKS", 0)
        self._open_n = 0
        self._open_hits = 0
        self.adc_open = False
        pad = _PADS_BANK0 + 4 + 4 * board.ADC_PIN
        self._pad_set = pad + 0x2000
        self._pad_clr = pad + 0x3000
        self._mem32 = getattr(machine, "mem32", None)
        if self._mem32 is None:
            self._open_every = 0
        # motor supply through a divider on a second ADC channel (-1: none)
        self._vsup = None
        if getattr(board, "VSUP_ADC_PIN", -1) >= 0:
            self._vsup = machine.ADC(machine.Pin(board.VSUP_ADC_PIN))
            self._vsup_read = self._vsup.read_u16
            # mV = (raw12 * mul) >> 12 (small ints: 4095 * mul < 2**30 up to 1 kV full scale)
            self._vsup_mul = (board.ADC_VREF_MV * board.VSUP_DIV_NUM * 4096 + board.VSUP_DIV_DEN * 4095 // 2) \
                // (board.VSUP_DIV_DEN * 4095)
            self.read_supply_mv = self._read_supply_mv
        pa = machine.Pin(board.ENC_A_PIN, machine.Pin.IN, machine.Pin.PULL_UP)
        machine.Pin(board.ENC_B_PIN, machine.Pin.IN, machine.Pin.PULL_UP)
        self._sm = rp2.StateMachine(board.ENC_PIO_SM, _quadrature, in_base=pa)
        self._sm.active(1)
        self._pwm = machine.PWM(machine.Pin(board.PWM_PIN))
        self._pwm.freq(board.PWM_FREQ)
        self._pwm.duty_u16(0)
        self._dir = machine.Pin(board.DIR_PIN, machine.Pin.OUT, value=0)
        self._dir_now = 0
        self._mem = getattr(machine, "mem32", None)
        self._intr = _PWM_INTR
        self._wrap_bit = 1 << ((board.PWM_PIN >> 1) & 7)
        # driver enable: low until the supervisor balances (App: set_enable); on the rp2 port
        # through the dead-man state machine (_dead_man), elsewhere a plain output
        self._en = None
        self._en_value = self._nop
        self._dm = None
        self._dm_pct = getattr(board, "DEADMAN_PCT", 175)
        if board.EN_PIN >= 0 and not (sys.platform == "rp2" and self._dead_man(board)):
            self._en = machine.Pin(board.EN_PIN, machine.Pin.OUT, value=0)
            self._en_value = self._en.value
        self._msign = board.MOTOR_SIGN
        # e-stop input (active low, pulled up): a hard IRQ on the falling edge cuts PWM and
        # enable at once and leaves _hit for estop(); the loop also polls the level
        self._hit = False
        self._estop_pin = None
        if getattr(board, "ESTOP_PIN", -1) >= 0:
            self._estop_pin = machine.Pin(board.ESTOP_PIN, machine.Pin.IN, machine.Pin.PULL_UP)
            self._estop_value = self._estop_pin.value
            self._estop_cb = self._on_estop
            if hasattr(self._estop_pin, "irq"):
                self._estop_pin.irq(handler=self._estop_cb, trigger=machine.Pin.IRQ_FALLING, hard=True)
        self._wdt = None
        self.wdt_feed = self._nop
        # cached bound methods
        self._read_u16 = self._adc.read_u16
        self._rx_fifo = self._sm.rx_fifo
        self._get = self._sm.get
        self._duty_u16 = self._pwm.duty_u16
        self._dir_value = self._dir.value
        # the clock the loop reads several times a tick: time.ticks_us itself (same values),
        # not a method around it (CPython tests: the method); likewise ticks_diff
        if hasattr(time, "ticks_us"):
            self.ticks_us = time.ticks_us
            self.ticks_diff = time.ticks_diff
        # the register fast paths (rp2 port only; CPython stand-ins run the methods below),
        # and the port's own tick arithmetic for App.run/Timing (C: a third of the cost of
        # fixmath's, the same values for this 2**30 clock)
        self._io = None
        if sys.platform == "rp2" and self._mem is not None and board.PWM_PIN < 30:
            self._fast(board, k)
            self.ticks_diff_fast = time.ticks_diff
            self.ticks_add_fast = time.ticks_add

    def _dead_man(self, board):
        # start-up, rp2 port: EN driven by the _deadman state machine on PIO1 (the encoder's
        # program fills PIO0).  EN is an output, low, from here on; False: no dead-man
        # configured (board.DEADMAN_SM -1), EN a plain output
        n = getattr(board, "DEADMAN_SM", -1)
        if n < 4 or n > 7 or self._mem is None or board.PWM_PIN >= 30:
            return False
        sm = rp2.StateMachine(n, _deadman, freq=_DM_HZ, set_base=machine.Pin(board.EN_PIN))
        # STATUS_SEL = TX FIFO, STATUS_N = 1: `mov x, status` reads all ones when it is empty
        a = _PIO1_EXECCTRL + 0x18 * (n & 3)
        self._mem[a] = (self._mem[a] & ~0x1F) | 1
        self._dm = sm
        self._dm_sm = n & 3
        self._dm_n = _DM_FOREVER
        sm.active(1)
        return True

    def _fast(self, board, k):
        # start-up: the state of the viper I/O paths, then they replace the methods
        io = array("i", [0] * _IO_N)
        io[_IO_OS_N] = self._os_n
        io[_IO_OS_K] = k
        io[_IO_OPEN_EVERY] = self._open_every
        io[_IO_DIR] = self._dir_now
        io[_IO_MSIGN] = self._msign
        io[_IO_ADC_CH] = board.ADC_PIN - 26
        io[_IO_SM] = board.ENC_PIO_SM & 3
        io[_IO_PIO] = (board.ENC_PIO_SM >> 2) & 1
        io[_IO_SLICE] = (board.PWM_PIN >> 1) & 7
        io[_IO_CHAN] = board.PWM_PIN & 1
        io[_IO_ESTOP] = -1 if self._estop_pin is None else board.ESTOP_PIN
        io[_IO_DM_SM] = -1
        self._io = io
        if self._dm is not None:
            io[_IO_DM_SM] = self._dm_sm
            io[_IO_DM_N] = self._dm_n
            self._en_value = self._dm_put
            self._dm_put(0)  # EN low, IRQ flag clear: the state the loop starts from
        self.read_angle_raw = self._read_angle_v
        self.read_encoder = self._read_encoder_v
        self.set_motor = self._set_motor_v
        self.estop = self._estop_v
        if self._vsup is not None:
            io[_IO_VSUP_CH] = board.VSUP_ADC_PIN - 26
            io[_IO_VSUP_MUL] = self._vsup_mul
            self.read_supply_mv = self._supply_v

    @micropython.viper
    def _read_angle_v(self) -> int:
        # read_angle_raw on the ADC registers (CS at 0x4004C000, RESULT at +4): as
        # machine.ADC.read_u16 does (select the input, START_ONCE, wait for READY), n times;
        # the 12-bit counts summed and floored (their exact mean for a constant input)
        s = ptr32(self._io)
        a = ptr32(0x4004C000)
        cs = (a[0] & (-0x700D)) | (s[_IO_ADC_CH] << 12)  # AINSEL, START_ONCE/MANY cleared
        n = s[_IO_OS_N]
        acc = 0
        while n > 0:
            a[0] = cs | 4
            w = _SPINS
            while w > 0 and not (a[0] & 0x100):
                w -= 1
            acc += a[1] & 0xFFF
            n -= 1
        v = acc >> s[_IO_OS_K]
        e = s[_IO_OPEN_EVERY]
        if e > 0:
            c = s[_IO_OPEN_N] + 1
            if c >= e:
                s[_IO_OPEN_N] = 0
                self._open_test(v)
            else:
                s[_IO_OPEN_N] = c
        return v

    @micropython.viper
    def _supply_v(self) -> int:
        # _read_supply_mv on the ADC registers (one conversion of the divider's input)
        s = ptr32(self._io)
        a = ptr32(0x4004C000)
        a[0] = (a[0] & (-0x700D)) | (s[_IO_VSUP_CH] << 12) | 4
        w = _SPINS
        while w > 0 and not (a[0] & 0x100):
            w -= 1
        return ((a[1] & 0xFFF) * s[_IO_VSUP_MUL]) >> 12

    @micropython.viper
    def _read_encoder_v(self) -> int:
        # read_encoder on the PIO registers (FSTAT +4, FLEVEL +0xC, RXF0 +0x20): FIFO level
        # + 1 values, each taken once the FIFO is not empty (bounded waits)
        s = ptr32(self._io)
        sm = s[_IO_SM]
        p = ptr32((0x5020 + (s[_IO_PIO] << 4)) << 16)  # PIO0/PIO1 base (no big-int literal in arithmetic)
        lvl = (p[3] >> (sm * 8 + 4)) & 0xF
        empty = 1 << (sm + 8)
        v = 0
        while lvl >= 0:
            w = _SPINS
            while w > 0 and (p[1] & empty):
                w -= 1
            v = p[8 + sm]
            lvl -= 1
        return v & 0xFFFF

    @micropython.viper
    def _set_motor_v(self, duty: int):
        # set_motor with the compare register written directly (machine.PWM.duty_u16's
        # rounding: cc = (du * (TOP + 1) + 32767) // 65535, the division done exactly by
        # shifts for the products below 2**31); a reversal takes the method's path
        if self._hit:
            duty = 0  # the e-stop fired since the loop last looked
        s = ptr32(self._io)
        if s[_IO_MSIGN] < 0:
            duty = -duty
        d = 0
        if duty < 0:
            d = 1
            duty = -duty
        if d != s[_IO_DIR]:
            self._reverse(d)
        if duty > 32767:
            duty = 32767
        b = 0x4005  # PWM base, shifted at run time (a folded constant would be a big int)
        pw = ptr32((b << 16) + s[_IO_SLICE] * 20)
        top = pw[4] & 0xFFFF
        if top > 0x7FFF:
            self._duty_u16(duty << 1)
        else:
            x = (duty << 1) * (top + 1) + 32767
            cc = (x + (x >> 16) + 1) >> 16
            if s[_IO_CHAN]:
                pw[3] = (pw[3] & 0xFFFF) | (cc << 16)
            else:
                pw[3] = (pw[3] & (-0x10000)) | cc
        # the dead-man's refresh (the loop is alive: it just commanded the motor): while the
        # driver is enabled, one word into the state machine's TX FIFO (dropped when full:
        # the machine takes one every 16 us).  An expiry since the last refresh is counted.
        # An e-stop IRQ between the DM_ON test and the write leaves EN on with compare 0 (it
        # wrote that after this call's compare) until the next tick latches F_ESTOP
        if s[_IO_DM_ON]:
            sm = s[_IO_DM_SM]
            b = 0x5030
            p = ptr32(b << 16)
            f = 1 << sm
            if p[12] & f:
                p[12] = f
                s[_IO_DM_TRIPS] = s[_IO_DM_TRIPS] + 1
            if not (p[1] & (f << 16)):
                p[4 + sm] = s[_IO_DM_N]

    @micropython.viper
    def _dm_put(self, on: int):
        # the driver enable through the dead-man (set_enable, off, the e-stop IRQ: no
        # allocation): 1 -> a refresh word (EN high for DEADMAN_PCT % of a period unless
        # refreshed), 0 -> the word 0 (EN low within one 16 us loop).  The IRQ flag is cleared
        s = ptr32(self._io)
        sm = s[_IO_DM_SM]
        b = 0x5030  # PIO1 base, shifted at run time (a folded constant would be a big int)
        p = ptr32(b << 16)
        w = 0
        d = 0
        if on:
            w = s[_IO_DM_N]
            d = 1
        s[_IO_DM_ON] = d
        p[12] = 1 << sm  # IRQ (0x030): write 1 to clear
        full = 1 << (16 + sm)  # FSTAT TXFULL
        n = _SPINS
        while n > 0 and (p[1] & full):
            n -= 1
        p[4 + sm] = w  # TXFn (0x010 + 4 n)

    @micropython.viper
    def _estop_v(self) -> bool:
        # estop on the SIO GPIO_IN register
        hit = self._hit
        self._hit = False
        if hit:
            return True
        pin = int(ptr32(self._io)[_IO_ESTOP])
        if pin < 0:
            return False
        return ((ptr32(0xD0000004)[0] >> pin) & 1) == 0

    def read_angle_raw(self):
        # ADC_OVERSAMPLE samples averaged (12-bit counts, floor: exact, see __init__); every ADC_OPEN_TEST_TICKS
        # calls, one more sample with the pad pulled toward the far rail (wiper test)
        rd = self._read_u16
        acc = 0
        for _ in range(self._os_n):
            acc += rd()
        v = acc >> self._os_shift
        if self._open_every > 0:
            self._open_n += 1
            if self._open_n >= self._open_every:
                self._open_n = 0
                self._open_test(v)
        return v

    def _open_test(self, v):
        # a connected wiper (source <= 12.5 kOhm for a pot <= 50 kOhm) against the pad's
        # ~50 kOhm pull moves by at most about a fifth of the way to the rail; an open one
        # goes (nearly) all the way.  Open: more than half way, on two tests in a row
        m = self._mem32
        if v < 2048:
            bit = _PUE
            far = 4095 - v
        else:
            bit = _PDE
            far = v
        m[self._pad_set] = bit
        self._read_u16()  # settle (one conversion)
        p = self._read_u16() >> self._adc_shift
        m[self._pad_clr] = bit
        moved = p - v if bit == _PUE else v - p
        if moved > (far >> 1) and far > 256:
            self._open_hits += 1
            if self._open_hits >= 2:
                self.adc_open = True
        else:
            self._open_hits = 0
            self.adc_open = False

    def _read_supply_mv(self):
        return ((self._vsup_read() >> 4) * self._vsup_mul) >> 12

    def read_encoder(self):
        # the latest count.  The program pushes on every sampling pass (a few cycles
        # apart), so `while rx_fifo(): get()` would never see the FIFO empty.  As
        # pico-examples' quadrature_encoder does: take FIFO level + 1 values -- the level
        # read once (at most the FIFO depth), the last get() waits for the next push,
        # which comes within one sampling pass: bounded time by construction, and the
        # value is the one the program pushed after this call began
        n = self._rx_fifo()
        v = self._get()
        while n > 0:
            v = self._get()
            n -= 1
        return v & 0xFFFF

    def set_motor(self, duty):
        if self._hit:
            duty = 0  # the e-stop fired since the loop last looked
        if self._msign < 0:
            duty = -duty
        d = 0
        if duty < 0:
            d = 1
            duty = -duty
        if d != self._dir_now:
            self._reverse(d)
        if duty > 32767:
            duty = 32767
        # 0..32767 -> 0..65534 of the PWM period
        self._duty_u16(duty << 1)

    def _reverse(self, d):
        # never reverse under drive: duty 0 first, and DIR only once 0 is in force (the
        # compare register is double-buffered: it takes effect at the next PWM wrap)
        self._duty_u16(0)
        m = self._mem
        if m is not None:
            b = self._wrap_bit
            m[self._intr] = b
            n = _WRAP_SPINS
            while n > 0 and not (m[self._intr] & b):
                n -= 1
        self._dir_value(d)
        self._dir_now = d
        if self._io is not None:
            self._io[_IO_DIR] = d

    def set_enable(self, on):
        # driver enable (EN/nSLEEP): 1 only while balancing (the supervisor decides).  With
        # the dead-man (rp2 port), EN then stays high only while set_motor is called at least
        # every DEADMAN_PCT % of a loop period (set_period)
        if on and self._hit:
            on = 0
        self._en_value(on)

    def set_period(self, us):
        # the control loop's period (App, from its gain table): the dead-man's timeout is
        # DEADMAN_PCT % of it from the last refresh (N + 1 loops of 16 us)
        n = (self._dm_pct * us) // (100 * _DM_LOOP_US) - 1
        if n < 1:
            n = 1
        self._dm_n = n
        if self._io is not None and self._dm is not None:
            self._io[_IO_DM_N] = n

    def deadman_trips(self):
        # dead-man expiries the refresh has seen since start-up (the driver was cut because
        # the loop was late or hung, and the loop came back); 0 without a dead-man
        return self._io[_IO_DM_TRIPS] if self._io is not None and self._dm is not None else 0

    def estop(self):
        # True while the e-stop input is low, or if its IRQ fired since the last call
        hit = self._hit
        self._hit = False
        if self._estop_pin is None:
            return hit
        return hit or not self._estop_value()

    def _on_estop(self, pin):
        # hard IRQ (no allocation): motor off and driver disabled now; the loop latches F_ESTOP
        self._hit = True
        self._duty_u16(0)
        self._en_value(0)

    def _nop(self, *a):
        pass

    # ---- hardware watchdog and the reset-cause marker ----
    def wdt_start(self, ms):
        # start (or re-time) machine.WDT; from now on only wdt_feed() keeps the board alive
        self._wdt = machine.WDT(timeout=ms)
        self.wdt_feed = self._wdt.feed

    def wdt_stop(self):
        # a deliberate stop (bounded run, Ctrl-C): machine.WDT cannot be stopped, the
        # register can (CTRL.ENABLE cleared through its atomic-clear alias)
        if self._mem is not None:
            self._mem[_WD_CTRL_CLR] = _WD_ENABLE
        self._wdt = None
        self.wdt_feed = self._nop

    def guard_timer(self):
        # a one-shot machine.Timer (the rp2 port's: its callback is scheduled from the alarm
        # interrupt and runs in the main thread at its next bytecode) for admit.py's guard over
        # a user hook; made once, by set_user, outside the loop
        return machine.Timer()

    def mark(self, cause):
        # the reset cause to report if the board resets from now on (msgtable.RC_*)
        if self._mem is not None:
            self._mem[_WD_SCRATCH3] = _MARK | cause

    def reset_cause(self):
        # at boot: the marker left before the reset (RC_POWER_ON when none), then cleared
        m = self._mem
        if m is None:
            return 0
        v = m[_WD_SCRATCH3]
        m[_WD_SCRATCH3] = 0
        if (v & 0x7FFFFF00) == _MARK:
            return v & 0xFF
        return 0

    def reset(self):
        machine.reset()

    def ticks_us(self):
        return time.ticks_us()

    def ticks_ms(self):
        return time.ticks_ms()

    def ticks_diff(self, a, b):
        return time.ticks_diff(a, b)

    def uart(self):
        # the host-link UART of the board config (start-up only).  Receive buffer: the
        # link reads at most 64 bytes a tick, so a burst of commands waits here (1024
        # bytes = 10 ms of line at 1 Mbaud); transmit buffer: a tick's telemetry,
        # heartbeat and replies go out without write() waiting for the line
        b = self.b
        u = machine.UART(b.UART_ID, b.UART_BAUD, tx=machine.Pin(b.UART_TX_PIN), rx=machine.Pin(b.UART_RX_PIN),
                         rxbuf=b.UART_RXBUF, txbuf=b.UART_TXBUF)
        # the receive interrupt at half the 32-byte FIFO, not MicroPython's 1/8: at 1 Mbaud a
        # burst of commands otherwise interrupts the loop every 4 bytes (40 us), each interrupt
        # ~35 us of handler from flash on a predicted Pico -- the loop got one eighth of the CPU
        # for the burst's length and a tick went late.  16 bytes (160 us) still leave the
        # handler 160 us before the FIFO could overflow; the receive timeout interrupt takes the
        # tail of a frame as before.  UARTIFLS (RP2040 datasheet 4.2.8): RXIFLSEL bits 5:3
        ifls = _UART_BASE[b.UART_ID] + _UARTIFLS
        machine.mem32[ifls] = (machine.mem32[ifls] & ~0x38) | (_RX_HALF << 3)
        return u

    def can(self):
        # the MCP2515 CAN controller of the board config (start-up only): SPI mode 0, CS idle
        # high, INT an input with pull-up (the module's INT is open drain on some boards)
        from .mcp2515 import MCP2515
        b = self.b
        spi = machine.SPI(b.CAN_SPI_ID, baudrate=b.CAN_SPI_HZ, polarity=0, phase=0, sck=machine.Pin(b.CAN_SCK_PIN),
                          mosi=machine.Pin(b.CAN_MOSI_PIN), miso=machine.Pin(b.CAN_MISO_PIN))
        cs = machine.Pin(b.CAN_CS_PIN, machine.Pin.OUT, value=1)
        irq = machine.Pin(b.CAN_INT_PIN, machine.Pin.IN, machine.Pin.PULL_UP) if b.CAN_INT_PIN >= 0 else None
        return MCP2515(spi, cs, irq)

    def off(self):
        # motor off and driver disabled (on exit / exception)
        self._duty_u16(0)
        self._en_value(0)
