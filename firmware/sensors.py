# Sensor conversion: raw ADC and 16-bit encoder counts -> controller inputs in the
# state LSB of firmware/gains.py, with the plausibility flags the supervisor reads.
#
#   phi counts = adc_sign * (adc - pot_offset)     -> yp = clamp(counts, YLIM_phi) << QP
#   encoder    = 16-bit counter, unwrapped by the signed difference of two readings
#                (|step| < 32768 counts per tick), accumulated into pos (saturating)
#                -> yx = clamp(pos, YLIM_x) << QX
# Flags: rail (ADC at 0 or full scale: open or shorted potentiometer), jump (encoder
# step larger than the fastest the cart can move in one tick: noise or a lost count).

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

_ENC_MASK = const(0xFFFF)
_ENC_HALF = const(0x8000)
_ENC_MOD = const(0x10000)
# pos saturates here (counts): far beyond any track, far inside the small ints
_POS_MAX = const(0x3FFFFF)


class Sensors:
    def __init__(self, t, off, adc_sign=1, enc_sign=1, pot_offset=None):
        self.adc_sign = -1 if adc_sign < 0 else 1
        self.enc_sign = -1 if enc_sign < 0 else 1
        self.pot_offset = 0
        self.load(t, off)
        if pot_offset is not None:
            self.pot_offset = pot_offset
        self.last = 0
        self.pos = 0
        self.counts = 0
        self.yx = 0
        self.yp = 0
        self.rail = False
        self.jump = False
        self.delta = 0
        self.primed = False
        # gear play: the encoder reads the motor side; yx follows it through a play operator of
        # half-width play (counts; 0: none), the wheel side's estimate wpos -- only where the
        # controller has no gap model (appparams: it finds the wheel side itself otherwise)
        self.play = 0
        self.wpos = 0

    def load(self, t, off):
        # conversion constants from a gain table (start-up / gain upload)
        self.qx = t[off["FMT"]]
        self.qp = t[off["FMT"] + 1]
        self.ylx = t[off["YLIM"]]
        self.ylp = t[off["YLIM"] + 1]
        self.pot_offset = t[off["CAL"]]
        self.adc_max = t[off["CAL"] + 1]
        self.encj = t[off["ENCJ"]]

    def zero(self):
        # the current cart position becomes x = 0
        self.pos = 0
        self.wpos = 0
        self.yx = 0

    def follow(self, enc):
        # between ticks, after a pause of the loop (a save's flash writes, a heap walk: tens of
        # ms): the encoder's counts since the last reading go into pos without the one-tick
        # jump check (a coasting cart rolls many ticks' worth in a pause); never in the tick
        enc &= _ENC_MASK
        if self.primed:
            dl = (enc - self.last) & _ENC_MASK
            if dl >= _ENC_HALF:
                dl -= _ENC_MOD
            if self.enc_sign < 0:
                dl = -dl
            v = self.pos + dl
            if v > _POS_MAX:
                v = _POS_MAX
            elif v < -_POS_MAX:
                v = -_POS_MAX
            self.pos = v
        self.last = enc

    def update(self, adc, enc):
        # one reading of both sensors (any ints: out-of-range values are clamped/masked)
        am = self.adc_max
        if adc <= 0:
            adc = 0
            self.rail = True
        elif adc >= am:
            adc = am
            self.rail = True
        else:
            self.rail = False
        c = adc - self.pot_offset
        if self.adc_sign < 0:
            c = -c
        self.counts = c
        l = self.ylp
        if c > l:
            c = l
        elif c < -l:
            c = -l
        self.yp = c << self.qp
        enc &= _ENC_MASK
        if self.primed:
            dl = (enc - self.last) & _ENC_MASK
            if dl >= _ENC_HALF:
                dl -= _ENC_MOD
        else:
            dl = 0
            self.primed = True
        self.last = enc
        if self.enc_sign < 0:
            dl = -dl
        self.delta = dl
        j = self.encj
        self.jump = dl > j or dl < -j
        v = self.pos + dl
        if v > _POS_MAX:
            v = _POS_MAX
        elif v < -_POS_MAX:
            v = -_POS_MAX
        self.pos = v
        l = self.play
        if l:
            w = self.wpos
            if v - w > l:
                w = v - l
            elif v - w < -l:
                w = v + l
            self.wpos = w
            v = w
        l = self.ylx
        if v > l:
            v = l
        elif v < -l:
            v = -l
        self.yx = v << self.qx
