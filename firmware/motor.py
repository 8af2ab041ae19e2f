# Force command -> motor duty: the inverse of the DC-motor/H-bridge model (sim/motor.py)
#   duty = (F R r/(n gear kt) + kt gear xdot/r) / V_supply * 32767
# in fixed point: duty = (KDU u + KDV vh) >> SD, where vh is the controller's estimate of
# the cart speed now (back-EMF compensation), then the deadband compensation in the
# direction of the force, then the clamp to +-max_duty (the supply-voltage limit).

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

DUTY_MAX = const(32767)


class Motor:
    def __init__(self, t, off, deadband=None, backemf=True):
        # deadband: duty counts added in the direction of the force (None: the table's)
        self.backemf = backemf
        self.max_duty = DUTY_MAX
        self.load(t, off)
        if deadband is not None:
            self.deadband = deadband

    def load(self, t, off):
        o = off["MOT"]
        self.kdu = t[o]
        self.kdv = t[o + 1]
        self.sd = t[o + 2]
        self.half = (1 << (self.sd - 1)) if self.sd > 0 else 0
        self.deadband = t[o + 3]

    def duty(self, u, vh):
        # u: force (u LSB, clamped by the controller); vh: cart speed (xdot LSB, clamped)
        acc = self.kdu * u + self.half
        if self.backemf:
            acc += self.kdv * vh
        d = acc >> self.sd
        if u > 0:
            d += self.deadband
        elif u < 0:
            d -= self.deadband
        l = self.max_duty
        if d > l:
            return l
        if d < -l:
            return -l
        return d
