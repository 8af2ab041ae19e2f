# Identification excitation played by the firmware itself (EXCITE command; issue 15 item 4).
#
# A maximum-length PRBS (15-bit Fibonacci LFSR x^15 + x^14 + 1, period 32767 bits), each bit
# held for `div` control ticks, of amplitude +-amp in the controller's force LSB:
#   mode 1 (EXC_ADD):  added to the controller's force while balancing (closed loop: the
#                      balancing run of `upright identify`); the sum is clamped to the force
#                      clamp and stored in the predictor's force buffer, so the estimator
#                      knows the force that was applied;
#   mode 2 (EXC_OPEN): the force IS the excitation, the controller's output is not applied
#                      (open loop: the cart-only run, pendulum removed or locked upright);
#                      the duty then has no back-EMF compensation (duty ~ force).
# The app (firmware/app.py) bounds it: amp <= half the active table's force clamp (checked
# by start()), the sum never beyond the clamp, max_duty on the duty; the signal stops
# (`on` = 0) on disarm and on any fault.  While a mode is set, TELEM_STATE's x and phi
# carry the sensors as read this tick (not the filtered estimate), so a log records what
# `upright identify` needs; EXCITE mode 0 ends that.  Per tick: a counter, at each new bit
# one LFSR shift -- integers only, nothing allocated.  Nothing runs at import.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from .msgtable import EXC_ADD, EXC_OFF, EXC_OPEN, OK, R_OUT_OF_RANGE

_LFSR_MASK = const(0x7FFF)
_LFSR_SEED = const(1)
# largest shift used to turn mN into force LSB (10000 mN << 16 < 2**30)
_EU_MAX = const(16)
AMP_MAX_MN = const(10000)


class Excite:
    def __init__(self):
        self.mode = EXC_OFF
        self.on = 0
        self.amp = 0
        self.div = 1
        self.n = 0
        self.lfsr = _LFSR_SEED
        self.bits = 0

    def start(self, mode, amp_mn, div, eu, ulim):
        # mode 0 stops; otherwise amp_mn (mN) -> force LSB (2**-eu N), at most ulim // 2.
        # Returns OK or R_OUT_OF_RANGE
        if mode == EXC_OFF:
            self.stop()
            return OK
        if mode != EXC_ADD and mode != EXC_OPEN:
            return R_OUT_OF_RANGE
        if div < 1 or div > 255 or amp_mn < 1 or amp_mn > AMP_MAX_MN or eu < 0 or eu > _EU_MAX:
            return R_OUT_OF_RANGE
        a = ((amp_mn << eu) + 500) // 1000
        if a < 1 or a > (ulim >> 1):
            return R_OUT_OF_RANGE
        self.amp = a
        self.div = div
        self.n = 0
        self.lfsr = _LFSR_SEED
        self.bits = 0
        self.mode = mode
        self.on = 1
        return OK

    def stop(self):
        self.on = 0
        self.mode = EXC_OFF

    def next(self):
        # this tick's excitation (+-amp); a new bit every div ticks
        n = self.n - 1
        if n <= 0:
            s = self.lfsr
            s = ((s << 1) | (((s >> 14) ^ (s >> 13)) & 1)) & _LFSR_MASK
            self.lfsr = s
            b = self.bits
            self.bits = b + 1 if b < 0x3FFFFFFE else 0
            n = self.div
        self.n = n
        if self.lfsr & 1:
            return self.amp
        return -self.amp
