# Force command -> motor duty: the inverse of the DC-motor/H-bridge model (sim/motor.py)
#   duty = (F R r/(n gear kt) + kt gear xdot/r) / V_supply * 32767
# in fixed point: duty = (KDU u + KDV vh) >> SD, where vh is the controller's estimate of
# the cart speed now (back-EMF compensation), then the deadband compensation in the
# direction of the duty (of the force at duty 0), then -- when the app measures the motor supply -- the correction
# duty x V_nominal / V_measured (Q12, 1/4..4), then the clamp to +-max_duty (the supply limit).

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

DUTY_MAX = const(32767)
# supply correction (Q12): duty x nominal supply / measured supply
VS_ONE = const(4096)
_VS_MIN = const(1024)
_VS_MAX = const(16384)
# |duty| clamped here before the supply correction (x 16384 stays below 2**30)
_D_PRE = const(65535)


class Motor:
    def __init__(self, t, off, deadband=None, backemf=True):
        # deadband: duty counts added in the direction of the force (None: the table's)
        self.backemf = backemf
        self.max_duty = DUTY_MAX
        # nominal supply / measured supply in Q12 (VS_ONE: the supply the table assumes)
        self.vscale = VS_ONE
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

    def set_supply(self, mv, nominal_mv):
        # the measured supply (mV; outside the loop or once a tick: one division)
        if mv <= 0:
            vs = _VS_MAX
        else:
            vs = ((nominal_mv << 12) + (mv >> 1)) // mv
            if vs < _VS_MIN:
                vs = _VS_MIN
            elif vs > _VS_MAX:
                vs = _VS_MAX
        self.vscale = vs

    def duty(self, u, vh):
        # u: force (u LSB, clamped by the controller); vh: cart speed (xdot LSB, clamped)
        acc = self.kdu * u + self.half
        if self.backemf:
            acc += self.kdv * vh
        d = acc >> self.sd
        # in the direction of the duty (the bridge takes its deadband off |duty|: with the
        # back-EMF term the duty can oppose the force), of the force when the duty is 0
        if d > 0 or (d == 0 and u > 0):
            d += self.deadband
        elif d < 0 or u < 0:
            d -= self.deadband
        vs = self.vscale
        if vs != VS_ONE:
            # the table's KDU/KDV assume the nominal supply: scale to the measured one
            if d > _D_PRE:
                d = _D_PRE
            elif d < -_D_PRE:
                d = -_D_PRE
            d = (d * vs + 2048) >> 12
        l = self.max_duty
        if d > l:
            return l
        if d < -l:
            return -l
        return d
