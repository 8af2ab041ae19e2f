# The per-tick methods of Sensors, Supervisor, Motor, Timing, Pacer (and App._supply)
# compiled by MicroPython's viper emitter: App(config={"emitter": "viper"}) builds these
# subclasses instead of the plain ones (firmware/board.py EMITTER: the board's default; the
# serial link builds PacerV).  Same attributes, same results (tests/test_firmware_fasttick.py
# compares them with the plain methods on random and extreme inputs under the unix port's
# viper and under CPython); only the hot method is replaced.  On a 125 MHz M0+ a bytecode
# attribute access or arithmetic op costs about 1-2 us; in viper the arithmetic is a few
# cycles and only the attribute traffic remains, so each update costs about half.  Under
# CPython the decorator is a no-op (the bodies are plain Python with int() casts).  The
# WebAssembly port has no native emitter: import this module only when selected (as
# fastpath.py / fastframe.py).  Viper has no default arguments: SupervisorV.update takes
# all seven.
#
# Viper rules kept here: module constants are local const()s (a plain global is an
# object: no native arithmetic with it), big literals never take part in arithmetic, every
# value stays a small int as in the plain methods (the products are bounded the same way).

try:
    import micropython
    from micropython import const
except ImportError:  # CPython
    class micropython:
        @staticmethod
        def viper(f):
            return f

    def const(x):
        return x

    def ptr32(a):
        return a

from .motor import Motor
from .pacer import Pacer
from .sensors import Sensors
from .supervisor import Supervisor
from .timing import Timing

# supervisor states and flags (== supervisor.py's; the test checks)
_ARMED = const(1)
_BALANCING = const(2)
_FAULT = const(3)
_F_TILT = const(1)
_F_WATCHDOG = const(2)
_F_ADC_RAIL = const(4)
_F_ENC_JUMP = const(8)
_F_TRACK = const(16)
_F_GAINS = const(32)
_F_STALL = const(64)
_F_UNDERVOLT = const(4096)
CONSTS = {"ARMED": _ARMED, "BALANCING": _BALANCING, "FAULT": _FAULT, "F_TILT": _F_TILT, "F_WATCHDOG": _F_WATCHDOG,
          "F_ADC_RAIL": _F_ADC_RAIL, "F_ENC_JUMP": _F_ENC_JUMP, "F_TRACK": _F_TRACK, "F_GAINS": _F_GAINS,
          "F_STALL": _F_STALL, "F_UNDERVOLT": _F_UNDERVOLT}
# msgtable parameter indices (== msgtable's; the test checks)
_P_TELEM_DIV = const(5)
_P_HEARTBEAT_MS = const(6)
PARAMS = {"P_TELEM_DIV": _P_TELEM_DIV, "P_HEARTBEAT_MS": _P_HEARTBEAT_MS}
_POS_MAX = const(0x3FFFFF)  # sensors.py
_VS_ONE = const(4096)  # motor.py
_D_PRE = const(65535)
_U16 = const(65535)  # timing.py
_TICKS_MASK = const(0x3FFFFFFF)  # fixmath.ticks_diff, written out: no call
_TICKS_HALF = const(0x20000000)
_TICKS_HIGH = const(-0x40000000)


class SensorsV(Sensors):
    @micropython.viper
    def update(self, adc: int, enc: int):
        # Sensors.update
        am = int(self.adc_max)
        if adc <= 0:
            adc = 0
            self.rail = True
        elif adc >= am:
            adc = am
            self.rail = True
        else:
            self.rail = False
        c = adc - int(self.pot_offset)
        if int(self.adc_sign) < 0:
            c = -c
        self.counts = c
        lim = int(self.ylp)
        if c > lim:
            c = lim
        elif c < -lim:
            c = -lim
        self.yp = c << int(self.qp)
        enc = enc & 0xFFFF
        dl = 0
        if self.primed:
            dl = (enc - int(self.last)) & 0xFFFF
            if dl >= 0x8000:
                dl -= 0x10000
        else:
            self.primed = True
        self.last = enc
        if int(self.enc_sign) < 0:
            dl = -dl
        self.delta = dl
        j = int(self.encj)
        if dl > j or dl < -j:
            self.jump = True
        else:
            self.jump = False
        v = int(self.pos) + dl
        if v > _POS_MAX:
            v = _POS_MAX
        elif v < -_POS_MAX:
            v = -_POS_MAX
        self.pos = v
        lim = int(self.ylx)
        if v > lim:
            v = lim
        elif v < -lim:
            v = -lim
        self.yx = v << int(self.qx)


class SupervisorV(Supervisor):
    @micropython.viper
    def update(self, counts: int, pos: int, rail, jump, delta: int, duty: int, ext: int) -> bool:
        # Supervisor.update (every argument given: App.step passes all seven)
        f = ext
        if not self.ready:
            f |= _F_GAINS
        if rail:
            f |= _F_ADC_RAIL
        if jump:
            f |= _F_ENC_JUMP
        st = int(self.state)
        if st == _BALANCING:
            t = int(self.tilt_counts)
            if not rail and (counts > t or counts < -t):
                f |= _F_TILT
            t = int(self.track_counts)
            if pos > t or pos < -t:
                f |= _F_TRACK
            if int(self.stall_ticks) > 0:
                if delta != 0:
                    self.stall_count = 0
                else:
                    t = int(self.stall_duty)
                    if duty >= t or duty <= -t:
                        n = int(self.stall_count) + 1
                        self.stall_count = n
                        if n > int(self.stall_ticks):
                            f |= _F_STALL
        if (st == _ARMED or st == _BALANCING) and int(self.wd_ticks) > 0:
            n = int(self.wd_count) + 1
            self.wd_count = n
            if n > int(self.wd_ticks):
                f |= _F_WATCHDOG
        self.last = f
        if f:
            self.faults = int(self.faults) | f
            self.state = _FAULT
            return False
        if self.faults:
            self.state = _FAULT
            return False
        if st == _ARMED and self.timing_ok:
            t = int(self.arm_counts)
            if counts > -t and counts < t:
                self.state = _BALANCING
                self.stall_count = 0
                return True
        return False


class MotorV(Motor):
    @micropython.viper
    def duty(self, u: int, vh: int) -> int:
        # Motor.duty
        acc = int(self.kdu) * u + int(self.half)
        if self.backemf:
            acc += int(self.kdv) * vh
        d = acc >> int(self.sd)
        if u > 0:
            d += int(self.deadband)
        elif u < 0:
            d -= int(self.deadband)
        vs = int(self.vscale)
        if vs != _VS_ONE:
            if d > _D_PRE:
                d = _D_PRE
            elif d < -_D_PRE:
                d = -_D_PRE
            d = (d * vs + 2048) >> 12
        lim = int(self.max_duty)
        if d > lim:
            return lim
        if d < -lim:
            return -lim
        return d


class TimingV(Timing):
    # begin/end with the tick difference written out (fixmath.ticks_diff: the same values
    # for a clock whose period is a multiple of 2**30, whatever diff the app passed)
    @micropython.viper
    def begin(self, t: int):
        if self._have_last:
            per = (t - int(self.last_us)) & _TICKS_MASK
            if per >= _TICKS_HALF:
                per |= _TICKS_HIGH
            if per > int(self.period_max):
                self.period_max = per
            p = int(self.period_us)
            j = per - p
            if j < 0:
                j = -j
            if j > int(self.jitter_max):
                self.jitter_max = j
            if per > p + (p >> 1):
                n = int(self.overruns)
                if n < _U16:
                    self.overruns = n + 1
        self.last_us = t
        self._have_last = True

    @micropython.viper
    def end(self, t0: int, t1: int) -> int:
        ex = (t1 - t0) & _TICKS_MASK
        if ex >= _TICKS_HALF:
            ex |= _TICKS_HIGH
        if ex < 0:
            ex = 0
        if ex < int(self.step_min):
            self.step_min = ex
        if ex > int(self.step_max):
            self.step_max = ex
        if ex > int(self.period_us):
            n = int(self.overruns)
            if n < _U16:
                self.overruns = n + 1
        n = int(self.steps)
        if n < _U16:
            self.steps = n + 1
        if ex > _U16:
            ex = _U16
        s = int(self._sum) + ex
        n = int(self._n) + 1
        if n >= 1024:
            self.mean_us = s >> 10
            s = 0
            n = 0
        self._sum = s
        self._n = n
        return ex


class PacerV(Pacer):
    # Pacer.tick on the app's int32 params array (link_serial.SerialLink builds this for an
    # app with the viper emitter and a params array: Pacer._p set)
    @micropython.viper
    def tick(self):
        p = ptr32(self._p)
        div = p[_P_TELEM_DIV]
        hb = p[_P_HEARTBEAT_MS]
        sent = 0
        if div > 0:
            n = int(self._telem_left) - 1
            if n <= 0:
                n = div
                q = (int(self.seq) + 1) & 0xFF
                self.seq = q
                self.telemetry(q)
                if div > 1:
                    sent = 1
            self._telem_left = n
        if hb <= 0:
            return
        t = int(self._hb_us) + int(self.app.period_us)
        if t < hb * 1000 or sent:
            self._hb_us = t
            return
        self._hb_us = 0
        q = (int(self.seq) + 1) & 0xFF
        self.seq = q
        self.heartbeat(q)


class SupplyV:
    # App._supply in viper: App(config={"emitter": "viper"}) with a HAL that measures the
    # supply calls SupplyV(app).update in its place (the same state, kept on the app)
    def __init__(self, app):
        self.app = app
        self.read = app._read_vsup
        self.motor = app.motor

    @micropython.viper
    def update(self, st: int) -> int:
        app = self.app
        v = int(self.read())
        a = int(app._vsup_acc)
        if a < 0:
            a = v << 3
        else:
            a += v - (a >> 3)
        app._vsup_acc = a
        v = a >> 3
        if v != int(app.vsup_mv):
            app.vsup_mv = v
            self.motor.set_supply(v, app.vsup_nom)
        if v < int(app.vsup_min) and (st == _ARMED or st == _BALANCING):
            return _F_UNDERVOLT
        return 0
