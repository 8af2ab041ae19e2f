# The fixed-point discrete controller: Kalman filter of the delayed state, predictor
# over the stored forces, state feedback + reference precompensation (+ optional
# integral action with anti-windup).  Integer-only and allocation-free per step.
#
# It implements exactly host/design/discrete.py's DiscreteController in the integer scales
# of host/design/export.py (see the header of firmware/gains.py for formats and the headroom
# proof).  One step, with y in state LSB and r in x LSB, all clamped by the caller:
#   e = y - C p;  xf = clamp(p + (M e + rf) >> SM)
#   u = clamp((KF.xf + KB.b + KR r + KI integ) >> SK, +-ULIM)      (returned)
#   vh = clamp((KV.xf + KVB.b) >> SKV)                              (cart speed now)
#   p = clamp(xf + ((Ad - I) xf + Bd b0 + ra) >> SA);  b <- [b1 .. u]
# rf and ra carry each recursive row's remainder to the next tick (error feedback):
# a correction smaller than one LSB is delayed, never lost, so the estimator has no
# rounding dead zone (without it a cart speed below ~0.01 m/s never moved x).
# The state limits are the declared bounds of the proof, so clamping keeps every
# accumulator inside -2**30 .. 2**30-1 whatever the inputs.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from array import array

from . import fixmath
from .msgtable import OK, R_BAD_LENGTH, R_BAD_SHAPE, R_UNSTABLE

_INTEG_SHIFT = const(6)
_INTEG_HALF = const(32)
# firmware-side re-check of an uploaded table: largest shift, gain and bound accepted
_SHIFT_MAX = const(30)
_G_MAX = const(0xFFFFF)
_B_MAX = const(0x3FFFF)
# (2**30 - 1) >> 10: budget of a row in units of 1024
_BUDGET = const(0xFFFFF)


def layout_offsets(layout):
    # name -> offset in the flat table (called once at start-up)
    off = {}
    o = 0
    for name, n in layout:
        off[name] = o
        o += n
    return off, o


class Controller:
    def __init__(self, layout, flat):
        # layout/flat: gains.LAYOUT and gains.FLAT (or an uploaded table of the same shape)
        self.off, self.length = layout_offsets(layout)
        d = flat[self.off["HDR"] + 1]
        self.d = d
        self.lim = fixmath.zeros(4)
        self.m = fixmath.zeros(8)
        self.sm = fixmath.zeros(4)
        self.rf = fixmath.zeros(4)
        self.kf = fixmath.zeros(4)
        self.kb = fixmath.zeros(d if d > 0 else 1)
        self.kv = fixmath.zeros(4)
        self.kvb = fixmath.zeros(d if d > 0 else 1)
        self.ad = fixmath.zeros(16)
        self.bd = fixmath.zeros(4)
        self.sa = fixmath.zeros(4)
        self.ra = fixmath.zeros(4)
        self.p = fixmath.zeros(4)
        self.xf = fixmath.zeros(4)
        self.b = fixmath.zeros(d if d > 0 else 1)
        self.scratch = fixmath.zeros(self.length)
        self.ulim = 0
        self.rlim = 0
        self.ilim = 0
        self.kr = 0
        self.ki = 0
        self.sk = 0
        self.hk = 0
        self.skv = 0
        self.hkv = 0
        self.integ = 0
        self.u = 0
        self.u_raw = 0
        self.vh = 0
        # anti-windup by conditional integration (False only to show windup in tests)
        self.aw = True
        self.load(flat)

    # ---- table handling (not in the loop) ----
    def load(self, t):
        # copy a validated flat table into the working arrays
        o = self.off
        d = self.d
        for i in range(4):
            self.lim[i] = t[o["LIM"] + i]
            self.sm[i] = t[o["SM"] + i]
            self.kf[i] = t[o["KF"] + i]
            self.kv[i] = t[o["KV"] + i]
            self.bd[i] = t[o["BD"] + i]
            self.sa[i] = t[o["SA"] + i]
        for i in range(8):
            self.m[i] = t[o["M"] + i]
        for i in range(16):
            self.ad[i] = t[o["AD"] + i]
        for i in range(d):
            self.kb[i] = t[o["KB"] + i]
            self.kvb[i] = t[o["KVB"] + i]
        self.ulim = t[o["ULIM"]]
        self.rlim = t[o["RLIM"]]
        self.ilim = t[o["ILIM"]]
        self.kr = t[o["KR"]]
        self.ki = t[o["KI"]]
        self.sk = t[o["SK"]]
        self.hk = (1 << (self.sk - 1)) if self.sk > 0 else 0
        self.skv = t[o["SKV"]]
        self.hkv = (1 << (self.skv - 1)) if self.skv > 0 else 0
        self.reset(0, 0)

    def _start(self, s):
        # rounding/residual term (< 2**s) of a row with shift s, in units of 1024
        # (or -1: bad shift)
        if s < 0 or s > _SHIFT_MAX:
            return -1
        return ((1 << s) >> 10) + 1

    def _term(self, tot, g, b):
        # add the conservative bound of |g| * b (units of 1024); -1 once over budget
        if tot < 0:
            return tot
        if g < 0:
            g = -g
        if g > _G_MAX or b < 0 or b > _B_MAX:
            return -1
        tot += fixmath.bound_units(g, b)
        return tot if tot <= _BUDGET else -1

    def validate(self, t, n, version):
        # re-check an uploaded table (t: n ints) before it may replace the live one:
        # shape, limits, and the abs-sum bound of every row (host/design/export.py's proof)
        o = self.off
        if n != self.length or t[o["HDR"] + 2] != n:
            return R_BAD_LENGTH
        if t[o["HDR"]] != version or t[o["HDR"] + 1] != self.d:
            return R_BAD_SHAPE
        lim = o["LIM"]
        for i in range(4):
            if t[lim + i] <= 0 or t[lim + i] > _B_MAX:
                return R_UNSTABLE
        ul = t[o["ULIM"]]
        rl = t[o["RLIM"]]
        il = t[o["ILIM"]]
        if ul <= 0 or ul > _B_MAX or rl <= 0 or rl > _B_MAX or il <= 0 or il > _B_MAX:
            return R_UNSTABLE
        d = self.d
        ebx = 2 * t[lim]
        ebp = 2 * t[lim + 2]
        for i in range(4):
            tot = self._start(t[o["SM"] + i])
            tot = self._term(tot, t[o["M"] + 2 * i], ebx)
            tot = self._term(tot, t[o["M"] + 2 * i + 1], ebp)
            if tot < 0:
                return R_UNSTABLE
        tot = self._start(t[o["SK"]])
        tv = self._start(t[o["SKV"]])
        for j in range(4):
            tot = self._term(tot, t[o["KF"] + j], t[lim + j])
            tv = self._term(tv, t[o["KV"] + j], t[lim + j])
        for j in range(d):
            tot = self._term(tot, t[o["KB"] + j], ul)
            tv = self._term(tv, t[o["KVB"] + j], ul)
        tot = self._term(tot, t[o["KR"]], rl)
        tot = self._term(tot, t[o["KI"]], il)
        if tot < 0 or tv < 0:
            return R_UNSTABLE
        for i in range(4):
            tot = self._start(t[o["SA"] + i])
            for j in range(4):
                tot = self._term(tot, t[o["AD"] + 4 * i + j], t[lim + j])
            tot = self._term(tot, t[o["BD"] + i], ul)
            if tot < 0:
                return R_UNSTABLE
        # telemetry conversions: 5 gains on the state limits and the force limit
        to = o["TEL"]
        for j in range(5):
            tot = self._start(t[to + 5])
            tot = self._term(tot, t[to + j], ul if j == 4 else t[lim + j])
            if tot < 0 or t[to + 5] < 1:
                return R_UNSTABLE
        # motor: KDU u + KDV vh, then the deadband
        mo = o["MOT"]
        tot = self._start(t[mo + 2])
        tot = self._term(tot, t[mo], ul)
        tot = self._term(tot, t[mo + 1], t[lim + 1])
        if tot < 0 or t[mo + 3] < 0 or t[mo + 3] > 32767:
            return R_UNSTABLE
        return OK

    def reset(self, yx, yp):
        # start estimating from a measurement (at rest), empty force buffer, no integral
        p = self.p
        p[0] = fixmath.clamp(yx, self.lim[0])
        p[1] = 0
        p[2] = fixmath.clamp(yp, self.lim[2])
        p[3] = 0
        for i in range(4):
            self.xf[i] = p[i]
            self.rf[i] = 0
            self.ra[i] = 0
        b = self.b
        for i in range(len(b)):
            b[i] = 0
        self.integ = 0
        self.u = 0
        self.u_raw = 0
        self.vh = 0

    # ---- the hot path: one control tick, integers only, no allocation ----
    def step(self, yx, yp, r):
        p = self.p
        m = self.m
        lim = self.lim
        sm = self.sm
        rf = self.rf
        ex = yx - p[0]
        ep = yp - p[2]
        # filter: xf = p + M e
        l = lim[0]
        a = m[0] * ex + m[1] * ep + rf[0]
        q = a >> sm[0]
        rf[0] = a - (q << sm[0])
        x0 = p[0] + q
        if x0 > l:
            x0 = l
        elif x0 < -l:
            x0 = -l
        l = lim[1]
        a = m[2] * ex + m[3] * ep + rf[1]
        q = a >> sm[1]
        rf[1] = a - (q << sm[1])
        x1 = p[1] + q
        if x1 > l:
            x1 = l
        elif x1 < -l:
            x1 = -l
        l = lim[2]
        a = m[4] * ex + m[5] * ep + rf[2]
        q = a >> sm[2]
        rf[2] = a - (q << sm[2])
        x2 = p[2] + q
        if x2 > l:
            x2 = l
        elif x2 < -l:
            x2 = -l
        l = lim[3]
        a = m[6] * ex + m[7] * ep + rf[3]
        q = a >> sm[3]
        rf[3] = a - (q << sm[3])
        x3 = p[3] + q
        if x3 > l:
            x3 = l
        elif x3 < -l:
            x3 = -l
        xf = self.xf
        xf[0] = x0
        xf[1] = x1
        xf[2] = x2
        xf[3] = x3
        # force: state feedback on the prediction + reference (+ integral)
        kf = self.kf
        kv = self.kv
        acc = kf[0] * x0 + kf[1] * x1 + kf[2] * x2 + kf[3] * x3 + self.kr * r + self.hk
        vac = kv[0] * x0 + kv[1] * x1 + kv[2] * x2 + kv[3] * x3 + self.hkv
        b = self.b
        kb = self.kb
        kvb = self.kvb
        d = self.d
        for i in range(d):
            bi = b[i]
            acc += kb[i] * bi
            vac += kvb[i] * bi
        ki = self.ki
        if ki:
            acc += ki * self.integ
        u = acc >> self.sk
        self.u_raw = u
        l = self.ulim
        sat = 0
        if u > l:
            u = l
            sat = 1
        elif u < -l:
            u = -l
            sat = -1
        if ki:
            # conditional integration: never push further into a saturated force
            inc = (r - x0 + _INTEG_HALF) >> _INTEG_SHIFT
            push = inc if ki > 0 else -inc
            if not self.aw or not ((sat > 0 and push > 0) or (sat < 0 and push < 0)):
                v = self.integ + inc
                l = self.ilim
                if v > l:
                    v = l
                elif v < -l:
                    v = -l
                self.integ = v
        self.u = u
        v = vac >> self.skv
        l = lim[1]
        if v > l:
            v = l
        elif v < -l:
            v = -l
        self.vh = v
        # update: p = xf + (Ad - I) xf + Bd b0 (delta form), then shift the buffer
        if d > 0:
            b0 = b[0]
            for i in range(d - 1):
                b[i] = b[i + 1]
            b[d - 1] = u
        else:
            b0 = u
        ad = self.ad
        bd = self.bd
        sa = self.sa
        ra = self.ra
        a = ad[0] * x0 + ad[1] * x1 + ad[2] * x2 + ad[3] * x3 + bd[0] * b0 + ra[0]
        q = a >> sa[0]
        ra[0] = a - (q << sa[0])
        v = x0 + q
        l = lim[0]
        if v > l:
            v = l
        elif v < -l:
            v = -l
        p[0] = v
        a = ad[4] * x0 + ad[5] * x1 + ad[6] * x2 + ad[7] * x3 + bd[1] * b0 + ra[1]
        q = a >> sa[1]
        ra[1] = a - (q << sa[1])
        v = x1 + q
        l = lim[1]
        if v > l:
            v = l
        elif v < -l:
            v = -l
        p[1] = v
        a = ad[8] * x0 + ad[9] * x1 + ad[10] * x2 + ad[11] * x3 + bd[2] * b0 + ra[2]
        q = a >> sa[2]
        ra[2] = a - (q << sa[2])
        v = x2 + q
        l = lim[2]
        if v > l:
            v = l
        elif v < -l:
            v = -l
        p[2] = v
        a = ad[12] * x0 + ad[13] * x1 + ad[14] * x2 + ad[15] * x3 + bd[3] * b0 + ra[3]
        q = a >> sa[3]
        ra[3] = a - (q << sa[3])
        v = x3 + q
        l = lim[3]
        if v > l:
            v = l
        elif v < -l:
            v = -l
        p[3] = v
        return u
