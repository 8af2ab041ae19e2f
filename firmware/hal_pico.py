# HAL for the Raspberry Pi Pico (RP2040): potentiometer on an ADC pin, quadrature
# encoder decoded by a PIO state machine (no CPU per edge), PWM + DIR H-bridge.
# The only kind of module that imports machine; pins come from firmware/board.py.
#
# The PIO program is the pico-examples quadrature decoder (x4 decoding with a 16-entry
# jump table on the previous/current A,B state): the count lives in the Y register
# and its low 16 bits are pushed (noblock) on every change, so the CPU reads the
# latest value of a 16-bit counter -- exactly the wrapping counter the firmware
# expects (a push never exceeds 65535: no big ints).  The program fills all 32
# instruction slots, so it is loaded at offset 0 as its `mov(pc, isr)` jump table needs.

import machine
import rp2
import time


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


class HalPico:
    def __init__(self, board):
        self.b = board
        self._adc = machine.ADC(machine.Pin(board.ADC_PIN))
        self._adc_shift = board.ADC_SHIFT
        pa = machine.Pin(board.ENC_A_PIN, machine.Pin.IN, machine.Pin.PULL_UP)
        machine.Pin(board.ENC_B_PIN, machine.Pin.IN, machine.Pin.PULL_UP)
        self._sm = rp2.StateMachine(board.ENC_PIO_SM, _quadrature, in_base=pa)
        self._sm.active(1)
        self._pwm = machine.PWM(machine.Pin(board.PWM_PIN))
        self._pwm.freq(board.PWM_FREQ)
        self._pwm.duty_u16(0)
        self._dir = machine.Pin(board.DIR_PIN, machine.Pin.OUT, value=0)
        self._en = None
        if board.EN_PIN >= 0:
            self._en = machine.Pin(board.EN_PIN, machine.Pin.OUT, value=1)
        self._msign = board.MOTOR_SIGN
        # cached bound methods
        self._read_u16 = self._adc.read_u16
        self._rx_fifo = self._sm.rx_fifo
        self._get = self._sm.get
        self._duty_u16 = self._pwm.duty_u16
        self._dir_value = self._dir.value

    def read_angle_raw(self):
        return self._read_u16() >> self._adc_shift

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
        if self._msign < 0:
            duty = -duty
        if duty < 0:
            self._dir_value(1)
            duty = -duty
        else:
            self._dir_value(0)
        if duty > 32767:
            duty = 32767
        # 0..32767 -> 0..65534 of the PWM period
        self._duty_u16(duty << 1)

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
        return machine.UART(b.UART_ID, b.UART_BAUD, tx=machine.Pin(b.UART_TX_PIN), rx=machine.Pin(b.UART_RX_PIN),
                            rxbuf=b.UART_RXBUF, txbuf=b.UART_TXBUF)

    def off(self):
        # motor off and driver disabled (on exit / exception)
        self._duty_u16(0)
        if self._en is not None:
            self._en.value(0)
