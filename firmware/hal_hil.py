# HIL HAL: the board's sensors and motor are the link to the host's plant simulator.
#
# The only firmware module that knows about HIL.  The app sees an ordinary HAL:
#   read_angle_raw() -> ADC counts of the last HIL_SENSOR frame
#   read_encoder()   -> 16-bit encoder counter of the last HIL_SENSOR frame
#   set_motor(duty)  -> answered with one HIL_ACTUATOR frame (tick of the sensor frame
#                       it answers, duty, supervisor state, low 8 fault bits), sent
#                       when the step ends so it carries the step's final duty/state
#   ticks_us(), ticks_ms(), ticks_diff() -> the interpreter's clock
# The main (firmware/main_hil.py) feeds decoded HIL_SENSOR payloads to on_sensor()
# and, after each control step, calls end_tick(): every step answers with exactly one
# actuator frame (the last duty set, or the previous one if the step set none).
# Nothing here allocates after __init__.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from array import array

from . import msgtable as T
from .hal_base import Hal

_DUTY_MAX = const(32767)

try:
    from time import ticks_us as _ticks_us, ticks_ms as _ticks_ms, ticks_diff as _ticks_diff
except ImportError:  # CPython (unit tests)
    import time as _t

    def _ticks_us():
        return int(_t.perf_counter() * 1000000) & 0x3FFFFFFF

    def _ticks_ms():
        return int(_t.perf_counter() * 1000) & 0x3FFFFFFF

    def _ticks_diff(a, b):
        d = (a - b) & 0x3FFFFFFF
        return d - 0x40000000 if d & 0x20000000 else d


class HilHal(Hal):
    # sender: object with send(mid, seq, vals, voff) (framing.SerialTx, canframe.SerialCanTx)
    # status: callable filling arr[0] = state, arr[1] = faults (e.g. app.fill_heartbeat),
    #         set later with set_status() once the app exists
    def __init__(self, sender, adc0=2048, enc0=0):
        self.sender = sender
        self._status = None
        self._st = array("i", [0] * 8)
        self._tx = array("i", [0] * 4)
        self.adc = adc0
        self.enc = enc0
        self.tick = 0
        self.seq = 0
        self.duty = 0
        self.n_sensor = 0
        self.n_actuator = 0
        # True between a sensor frame and the actuator frame answering it
        self.pending = False

    def set_status(self, fill):
        self._status = fill

    # ---- from the link ----
    def on_sensor(self, tick, adc, enc, seq):
        self.tick = tick
        self.adc = adc
        self.enc = enc
        self.seq = seq
        self.pending = True
        self.n_sensor += 1

    # ---- the HAL interface ----
    def read_angle_raw(self):
        return self.adc

    def read_encoder(self):
        return self.enc

    def set_motor(self, duty):
        if duty > _DUTY_MAX:
            duty = _DUTY_MAX
        elif duty < -_DUTY_MAX:
            duty = -_DUTY_MAX
        # the answer goes out at end_tick(), after the step, so that it carries the
        # last duty of the step and the supervisor state the step ended in
        self.duty = duty

    def ticks_us(self):
        return _ticks_us()

    def ticks_ms(self):
        return _ticks_ms()

    def ticks_diff(self, a, b):
        return _ticks_diff(a, b)

    # hardware cut-offs of a board HAL (hal_pico): nothing to do on a link
    def set_enable(self, on):
        pass

    def wdt_start(self, ms):
        pass

    def wdt_feed(self):
        pass

    def wdt_stop(self):
        pass

    def mark(self, cause):
        pass

    # ---- from the main ----
    def end_tick(self):
        # answer the current sensor frame (once)
        if self.pending:
            self._answer()

    def _answer(self):
        self.pending = False
        st = self._st
        if self._status is not None:
            self._status(st)
        tx = self._tx
        tx[0] = self.tick
        tx[1] = self.duty
        tx[2] = st[0]
        tx[3] = st[1] & 0xFF
        self.n_actuator += 1
        self.sender.send(T.HIL_ACTUATOR, self.seq, tx, 0)
