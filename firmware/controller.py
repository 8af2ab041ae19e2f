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
#
# Catch mode (issue 15 item 3; host/design/catch.py): the table carries a second force row
# (KFC, KBC, KRC, KIC, SKC) and its clamp (CATCH[3]) for large tilts.  schedule(), called
# once per tick before step(), switches between the two by swapping the row's array
# pointers and scalars -- the estimator, the predictor and the stored forces are shared,
# so nothing else changes.  Tracking -> catch when |p_phi| > CATCH[0] (phi LSB; 0: off);
# catch -> tracking only once |p_phi| < CATCH[1], |p_phidot| < CATCH[8] (hysteresis) AND the rows, evaluated
# on the same (p, b, r), differ by at most CATCH[2] (u LSB): the hand-back is bumpless.
#
# Estimator per table (issue 27 item 3; host/design/export.py filter_gain): EST 0 is the full
# (Kalman) filter above; EST 1 the reduced-order observer in the same predictor-corrector
# form: x and phi are the measurements (xf0 = y_x, xf2 = y_phi: the filter rows of x and phi,
# the identity in the table, are skipped), xdot and phidot are corrected by Lr (M rows 1, 3),
# and p keeps the prediction of the measured states, which carries the Gopinath z = p_w - Lr p_y.

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
# lim: the state limits x, xdot, phi, phidot (LSB, from the table), then the gear-play model --
# its half-width (u LSB x ticks, 0: none) and the motor side's place in the play -- as words of
# the same array: the viper step reads them through its ptr32, not as attributes (an attribute
# read costs a board ~2.5 us, and the link's poll after the step has none to spare; and no
# properties on the class: with one, MicroPython looks every attribute store up in the class first)
LIM_GHB = const(4)
LIM_GAP = const(5)
# ... and the half play in x LSB, the cart's Coulomb friction in u LSB (the predictor's force while
# the motor side is in the play), then the gap model's last d values (oldest first): the wheel
# side the x measurement stands for is found from the gap at the measurement's time
LIM_HPX = const(6)
LIM_FC = const(7)
# ... the motor's KDU and KDV (the duty's sign: see the gap model in step) and the Coulomb
# compensation the duty carries in its own direction (u LSB, FC_COMP/32 of LIM_FC: the tables
# `upright commission` uploads add that much of the cart's Coulomb friction to their deadband
# compensation, host.operate.commission.COULOMB_COMP), then the gap history
LIM_KDU = const(8)
LIM_KDV = const(9)
LIM_FCC = const(10)
LIM_GH = const(11)
FC_COMP = const(29)
# crossing the play: while the gap is open toward the force, the force is raised to what reaches
# the flank, at most the clamp >> CROSS_SHIFT (a quarter: a stronger crossing hits the flank hard
# enough to break the 5 m/s^2 limit, a weaker one leaves the limit cycle; docs/parameters.md)
CROSS_SHIFT = const(2)


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
        self.lim = fixmath.zeros(LIM_GH + (d if d > 0 else 0))
        self.m = fixmath.zeros(8)
        self.sm = fixmath.zeros(4)
        self.rf = fixmath.zeros(4)
        # the force row in use (kf, kb, kr, ki, sk, hk, ulim) points at the tracking set
        # (kft ...) or the catch set (kfc ...): schedule() swaps them
        self.kft = fixmath.zeros(4)
        self.kbt = fixmath.zeros(d if d > 0 else 1)
        self.kfc = fixmath.zeros(4)
        self.kbc = fixmath.zeros(d if d > 0 else 1)
        self.kf = self.kft
        self.kb = self.kbt
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
        self.ulim_t = 0
        self.krt = 0
        self.kit = 0
        self.skt = 0
        self.hkt = 0
        self.ulim_c = 0
        self.krc = 0
        self.kic = 0
        self.skc = 0
        self.hkc = 0
        self.phi_on = 0  # catch mode thresholds (phi LSB; phi_on 0: no catch mode)
        self.phi_off = 0
        self.du = 0  # largest force step (u LSB) accepted at the hand-back
        # the live force clamp ulo <= u <= uhi: +-ulim while tracking; in catch mode a clamp
        # on the cart's acceleration, centred on -cphi * phi (>> sphi), |u| <= ucmax
        self.uhi = 0
        self.ulo = 0
        self.cphi = 0
        self.sphi = 0
        self.ucmax = 0
        # hand-back: the tracking row starts from the reference rr that makes its force
        # equal the catch row's (rr = r + ((uc - ut) * rg) >> srg), then rr moves to the set
        # reference by rstep x LSB per tick
        self.rr = 0
        self.ramp = False
        self.rstep = 0
        self.w_off = 0  # |phidot| (phidot LSB) below which the hand-back may happen
        self.rg = 0
        self.srg = 0
        self.emax = 0
        self.catching = False
        self.n_catch = 0  # catch-mode entries since the last load
        self.bump = 0  # force difference of the two rows at the latest hand-back (u LSB)
        self.skv = 0
        self.hkv = 0
        self.est = 0  # estimator: 0 full, 1 reduced-order (x, phi from the sensors)
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
            self.kft[i] = t[o["KF"] + i]
            self.kfc[i] = t[o["KFC"] + i]
            self.kv[i] = t[o["KV"] + i]
            self.bd[i] = t[o["BD"] + i]
            self.sa[i] = t[o["SA"] + i]
        for i in range(8):
            self.m[i] = t[o["M"] + i]
        for i in range(16):
            self.ad[i] = t[o["AD"] + i]
        for i in range(d):
            self.kbt[i] = t[o["KB"] + i]
            self.kbc[i] = t[o["KBC"] + i]
            self.kvb[i] = t[o["KVB"] + i]
        self.ulim_t = t[o["ULIM"]]
        self.rlim = t[o["RLIM"]]
        self.ilim = t[o["ILIM"]]
        self.krt = t[o["KR"]]
        self.kit = t[o["KI"]]
        self.skt = t[o["SK"]]
        self.hkt = (1 << (self.skt - 1)) if self.skt > 0 else 0
        ca = o["CATCH"]
        self.phi_on = t[ca]
        self.phi_off = t[ca + 1]
        self.du = t[ca + 2]
        self.ulim_c = t[ca + 3]
        self.cphi = t[ca + 4]
        self.sphi = t[ca + 5]
        self.ucmax = t[ca + 6]
        self.krc = t[o["KRC"]]
        self.kic = t[o["KIC"]]
        self.skc = t[o["SKC"]]
        self.hkc = (1 << (self.skc - 1)) if self.skc > 0 else 0
        self.rstep = t[ca + 7]
        self.w_off = t[ca + 8]
        # rg / 2**srg = 2**skt / krt (x LSB per u LSB).  emax: the largest force difference a
        # reference within +-rlim can absorb, |krt| * 2 rlim / 2**skt (u LSB) -- a stiff position
        # row turns the cart's distance from the reference after a catch into tens of newtons --
        # and |e| <= emax keeps e * rg small (srg below)
        k = self.krt if self.krt > 0 else -self.krt
        self.emax = ((k * 2 * self.rlim) >> self.skt) + 2
        self.rg = 0
        self.srg = 0
        if self.krt != 0:
            s = 0
            while s < 24:
                g = ((1 << (self.skt + s + 1)) + self.krt) // (2 * self.krt)
                if (g if g > 0 else -g) * self.emax > 0x1FFFFFFF:
                    break
                self.rg = g
                self.srg = s
                s += 1
        self.n_catch = 0
        self._use(False)
        self.skv = t[o["SKV"]]
        self.hkv = (1 << (self.skv - 1)) if self.skv > 0 else 0
        self.est = t[o["EST"]]
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
        if t[o["EST"]] != 0 and t[o["EST"]] != 1:
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
        # catch mode: thresholds within the tilt range, its clamp like ULIM; a stored force
        # is bounded by the larger clamp (ub) in every row that reads one
        ca = o["CATCH"]
        uc = t[ca + 3]
        if uc <= 0 or uc > _B_MAX or t[ca + 2] < 0 or t[ca + 2] > _B_MAX:
            return R_UNSTABLE
        if t[ca] < 0 or t[ca + 1] < 0 or t[ca + 1] > t[ca] or t[ca] > t[lim + 2]:
            return R_UNSTABLE
        # the clamp's centre: |cphi| * phi limit within budget, shift sane, ucmax >= ulim_c
        ucm = t[ca + 6]
        if ucm < uc or ucm > _B_MAX or self._term(self._start(t[ca + 5]), t[ca + 4], t[lim + 2]) < 0:
            return R_UNSTABLE
        if t[ca + 7] < 0 or t[ca + 7] > t[o["RLIM"]] or t[ca + 8] < 0:
            return R_UNSTABLE
        ub = ul if ul > ucm else ucm
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
        tc = self._start(t[o["SKC"]])
        for j in range(4):
            tot = self._term(tot, t[o["KF"] + j], t[lim + j])
            tv = self._term(tv, t[o["KV"] + j], t[lim + j])
            tc = self._term(tc, t[o["KFC"] + j], t[lim + j])
        for j in range(d):
            tot = self._term(tot, t[o["KB"] + j], ub)
            tv = self._term(tv, t[o["KVB"] + j], ub)
            tc = self._term(tc, t[o["KBC"] + j], ub)
        tot = self._term(tot, t[o["KR"]], rl)
        tot = self._term(tot, t[o["KI"]], il)
        tc = self._term(tc, t[o["KRC"]], rl)
        tc = self._term(tc, t[o["KIC"]], il)
        if tot < 0 or tv < 0 or tc < 0:
            return R_UNSTABLE
        for i in range(4):
            tot = self._start(t[o["SA"] + i])
            for j in range(4):
                tot = self._term(tot, t[o["AD"] + 4 * i + j], t[lim + j])
            tot = self._term(tot, t[o["BD"] + i], ub)
            if tot < 0:
                return R_UNSTABLE
        # telemetry conversions: 5 gains on the state limits and the force limit
        to = o["TEL"]
        for j in range(5):
            tot = self._start(t[to + 5])
            tot = self._term(tot, t[to + j], ub if j == 4 else t[lim + j])
            if tot < 0 or t[to + 5] < 1:
                return R_UNSTABLE
        # motor: KDU u + KDV vh, then the deadband
        mo = o["MOT"]
        tot = self._start(t[mo + 2])
        tot = self._term(tot, t[mo], ub)
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
        lim = self.lim
        lim[LIM_GAP] = 0  # the motor side in the middle of the play, no history (HPX, FC: parameters)
        for i in range(LIM_GH, len(lim)):
            lim[i] = 0
        self.ramp = False
        self._use(False)

    # ---- catch mode: which force row step() uses (allocation-free, integers only) ----
    def _use(self, catch):
        # point the force row at the catch set (True) or the tracking set (False)
        self.catching = catch
        if catch:
            self.kf = self.kfc
            self.kb = self.kbc
            self.kr = self.krc
            self.ki = self.kic
            self.sk = self.skc
            self.hk = self.hkc
            self.ulim = self.ulim_c
            self._clamp_c()
        else:
            self.kf = self.kft
            self.kb = self.kbt
            self.kr = self.krt
            self.ki = self.kit
            self.sk = self.skt
            self.hk = self.hkt
            self.ulim = self.ulim_t
            self.uhi = self.ulim_t
            self.ulo = -self.ulim_t

    def _clamp_c(self):
        # catch mode: the clamp of the cart acceleration as a force range from the tilt
        # estimate, u in [-ulim_c - sh, ulim_c - sh] with sh = cphi * phi >> sphi, |u| <= ucmax
        sh = (self.p[2] * self.cphi) >> self.sphi
        m = self.ucmax - self.ulim_c
        if sh > m:
            sh = m
        elif sh < -m:
            sh = -m
        self.uhi = self.ulim_c - sh
        self.ulo = -self.ulim_c - sh

    def _row(self, kf, kb, kr, ki, sk, hk, r):
        # a force row on the a-priori estimate p and the stored forces b (before clamping);
        # the same terms and bounds as step()'s force row (the headroom proof covers it)
        p = self.p
        acc = kf[0] * p[0] + kf[1] * p[1] + kf[2] * p[2] + kf[3] * p[3] + kr * r + hk
        b = self.b
        for i in range(self.d):
            acc += kb[i] * b[i]
        if ki:
            acc += ki * self.integ
        return acc >> sk

    def schedule(self, r):
        # once per tick before step(), returns the reference for step(): enter catch mode
        # on a large tilt; hand back to the tracking row once the tilt is small, from the
        # reference that makes both rows agree (within du), then ramp it to r
        ph = self.p[2]
        if not self.catching:
            on = self.phi_on
            if on > 0 and (ph > on or ph < -on):
                self._use(True)
                self.n_catch += 1
                self.ramp = False
                self._clamp_c()
                return r
            if self.ramp:
                q = self.rr
                st = self.rstep
                if q > r + st:
                    q -= st
                elif q < r - st:
                    q += st
                else:
                    q = r
                    self.ramp = False
                self.rr = q
                return q
            return r
        self._clamp_c()
        off = self.phi_off
        if ph >= off or ph <= -off:
            return r
        w = self.p[3]
        off = self.w_off
        if w >= off or w <= -off:
            return r
        uc = self._row(self.kfc, self.kbc, self.krc, self.kic, self.skc, self.hkc, r)
        if uc > self.uhi:
            uc = self.uhi
        elif uc < self.ulo:
            uc = self.ulo
        e = uc - self._row(self.kft, self.kbt, self.krt, self.kit, self.skt, self.hkt, r)
        l = self.emax
        if e > l:
            e = l
        elif e < -l:
            e = -l
        q = r + ((e * self.rg) >> self.srg)
        l = self.rlim
        if q > l:
            q = l
        elif q < -l:
            q = -l
        ut = self._row(self.kft, self.kbt, self.krt, self.kit, self.skt, self.hkt, q)
        l = self.ulim_t
        if ut > l:
            ut = l
        elif ut < -l:
            ut = -l
        e = ut - uc
        if -self.du <= e <= self.du:
            self.bump = e
            self._use(False)
            self.rr = q
            self.ramp = q != r
            return q
        return r

    # ---- the hot path: one control tick, integers only, no allocation ----
    def step(self, yx, yp, r):
        p = self.p
        m = self.m
        lim = self.lim
        sm = self.sm
        rf = self.rf
        l = lim[LIM_GHB]
        if l:
            # gear play: the encoder reads the motor side; the wheel side it stands for.  With the
            # motor side on a flank (the gap model at the measurement's time: d ticks back) the
            # wheel is half the play behind it; while it crosses the play the encoder says nothing
            # about the wheel but that it is within half the play of it: the prediction, held
            # inside that window.  Written out here, not a method: called from the viper step,
            # a bytecode method cost ~78 us a tick on a predicted Pico (docs/firmware.md)
            if self.d > 0:
                v = lim[LIM_GH]
            else:
                v = lim[LIM_GAP]
            h = lim[LIM_HPX]
            if v >= l:
                yx = yx - h
            elif v <= -l:
                yx = yx + h
            else:
                v = p[0] - yx
                if v > h:
                    v = h
                elif v < -h:
                    v = -h
                yx = yx + v
        ex = yx - p[0]
        ep = yp - p[2]
        est = self.est
        # filter: xf = p + M e (est 1, the reduced-order observer: x and phi are the measurements)
        l = lim[0]
        if est:
            x0 = yx
        else:
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
        if est:
            x2 = yp
        else:
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
        l = self.uhi
        sat = 0
        if u > l:
            u = l
            sat = 1
        else:
            l = self.ulo
            if u < l:
                u = l
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
        # gear play: the predictor is given the force the gear passes (ue), the part of u
        # beyond the flank of the play model gap (u LSB x ticks, +-ghb).  While the motor side
        # is off the flank u pushes toward, u is raised to what reaches that flank this tick,
        # at most the clamp >> CROSS_SHIFT (an inverse of the play: it is crossed in a few ticks
        # instead of at the slow speed a small force leaves the motor, and none of the raise
        # reaches the cart, which the gear does not drive until the flank)
        ue = u
        l = lim[LIM_GHB]
        if l:
            sv = lim[LIM_KDV] * v  # the duty's back-EMF term (v: vh, as just set)
            v = lim[LIM_GAP]
            if u > 0:
                w = l - v
                h = self.uhi >> CROSS_SHIFT
                if w > h:
                    w = h
                if u < w:
                    u = w
                    self.u = u
            elif u < 0:
                w = -l - v
                h = -((-self.ulo) >> CROSS_SHIFT)
                if w < h:
                    w = h
                if u > w:
                    u = w
                    self.u = u
            # the motor side moves against the wheel side by what the duty makes beyond the cart's
            # speed: u, and the Coulomb compensation the motor adds in the duty's direction (on a
            # flank it cancels the cart's friction; free in the play it drives the motor, with
            # the duty's sign even where the force's is the other -- braking a fast cart, the
            # back-EMF term outweighs the force)
            w = u
            fcc = lim[LIM_FCC]
            if fcc:
                sv = sv + lim[LIM_KDU] * u
                if sv > 0 or (sv == 0 and u > 0):
                    w = u + fcc
                elif sv < 0 or u < 0:
                    fcc = -fcc
                    w = u + fcc
                else:
                    fcc = 0
            v = v + w
            if v > l:
                # the force past the flank, less the compensation the cart's friction takes
                ue = v - l - fcc
                if ue < 0:
                    ue = 0
                v = l
            elif v < -l:
                ue = v + l - fcc
                if ue > 0:
                    ue = 0
                v = -l
            else:
                # in the play the gear drives nothing, and the cart's dry friction, which the
                # table's compensation cancels only through the gear, brakes it: the predictor is
                # given the Coulomb force against the estimated speed (without it the estimate
                # coasts on while the cart slows, and the back-EMF compensation turns that speed
                # error into force at the engagement: c_emf, 30-44 N s/m, x the error)
                ue = 0
                fc = lim[LIM_FC]
                if fc:
                    if p[1] > 0:
                        ue = -fc
                    elif p[1] < 0:
                        ue = fc
            lim[LIM_GAP] = v
            for i in range(d - 1):
                lim[LIM_GH + i] = lim[LIM_GH + 1 + i]
            if d > 0:
                lim[LIM_GH + d - 1] = v
        # update: p = xf + (Ad - I) xf + Bd b0 (delta form), then shift the buffer
        if d > 0:
            b0 = b[0]
            for i in range(d - 1):
                b[i] = b[i + 1]
            b[d - 1] = ue
        else:
            b0 = ue
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
