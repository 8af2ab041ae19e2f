# The app's parameters (msgtable PARAMS) and set-point: the derived integers each parameter
# sets (tilt and arm limits in ADC counts, the link watchdog and stall timeout in ticks, the
# period and link budget, the drive's signs and offset), PARAM_GET / PARAM_SET and
# SET_REFERENCE.  A part of firmware/app.py's App (class App(..., Params, ...)): the methods
# read and write the app's attributes; none runs in the control tick.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from . import admit
from . import fixmath
from . import msgtable as T
from .controller import FC_COMP, LIM_FC, LIM_FCC, LIM_GHB, LIM_HPX, LIM_KDU, LIM_KDV
from .supervisor import ARMED, BALANCING

# the parameters with a derived integer (Params._apply_param)
_DERIVED = (T.P_TILT_LIMIT, T.P_ARM_TILT, T.P_WATCHDOG_MS, T.P_MAX_DUTY, T.P_POT_OFFSET, T.P_ADC_SIGN,
            T.P_ENC_SIGN, T.P_MOTOR_SIGN, T.P_GEAR_PLAY, T.P_CART_COULOMB)
_SMALL = const(0x1FFFFFFF)


class Params:
    # ---- parameters -> derived integers (outside the loop) ----
    def _counts_from_mrad(self, mrad):
        o = self.off["TILT"]
        t = self.table
        return (mrad * t[o] + (1 << (t[o + 1] - 1))) >> t[o + 1]

    def _gap_ticks(self, half_x):
        # half the gear play in the controller's gap units (u LSB x ticks): the motor side
        # crosses the play at the no-load speed the force u leaves it (u KDU/KDV xdot LSB),
        # moving Ad[0][1] >> SA[0] x LSB per xdot LSB per tick:
        #   half_x x KDV/KDU x 2**SA[0] / Ad[0][1]
        # in small ints (every intermediate < 2**30; saturates at _SMALL)
        mo = self.motor
        t = self.table
        ad1 = t[self.off["AD"] + 1]
        if half_x <= 0 or mo.kdu <= 0 or mo.kdv <= 0 or ad1 <= 0:
            return 0
        r = (mo.kdv << 8) // mo.kdu
        if r <= 0 or half_x > _SMALL // r:
            return _SMALL
        n = half_x * r
        s = t[self.off["SA"]] - 8
        while s > 0 and n <= (_SMALL >> 1):
            n <<= 1
            s -= 1
        n //= ad1
        while s > 0:
            if n > (_SMALL >> 1):
                return _SMALL
            n <<= 1
            s -= 1
        while s < 0:
            n >>= 1
            s += 1
        return n

    def _force_u(self, cn):
        # a force in 0.01 N (telemetry's unit) in u LSB: the inverse of the telemetry's scale
        # (0.01 N = u m >> s), cn 2**s / m in small ints (saturates at _SMALL)
        o = self.off["TEL"]
        t = self.table
        m = t[o + 4]
        s = t[o + 5]
        if cn <= 0 or m <= 0:
            return 0
        n = cn
        while s > 0 and n <= (_SMALL >> 1):
            n <<= 1
            s -= 1
        n //= m
        while s > 0:
            if n > (_SMALL >> 1):
                return _SMALL
            n <<= 1
            s -= 1
        return n

    def _apply_params(self):
        # every derived integer, from the parameters and the active table: at start-up and
        # whenever the active table changes (upload, saved configuration) -- the period, the
        # link watchdog, the stall timeout (ticks at the table's rate), the tilt and track
        # limits (the table's scales)
        p = self.params
        sup = self.sup
        # the period comes only from the active table (loop_rate_hz reports it)
        rate = self.rate
        p[T.P_LOOP_RATE] = rate
        self.period_us = 1000000 // rate
        self.timing.period_us = self.period_us
        if self._has_period:
            self.hal.set_period(self.period_us)  # HalPico: the driver-enable dead-man's timeout
        # the link's per-tick budget (link_serial, link_can: admit.py): its frames end within
        # this many us of the step's scheduled start -- short of a late tick, 1.5 periods, by what
        # follows a frame before the next step starts: 1/8 of a period (a burst's receive
        # interrupts, a frame over its planned cost) and at least admit.REFILL_US (the loop's code
        # refilling the flash cache the frame evicted).  11/8 of the period at 250 Hz and below;
        # 5/4 (2500 us) at 500 Hz
        r = self.period_us >> 3
        if r < admit.REFILL_US:
            r = admit.REFILL_US
        self.link_budget_us = self.period_us + (self.period_us >> 1) - r
        sup.stall_ticks = (self.stall_ms * rate) // 1000
        sup.stall_duty = self.stall_duty + self.motor.deadband
        t = self.table
        # track fault at 1.25 x the reference limit (encoder counts)
        qx = t[self.off["FMT"]]
        rl = t[self.off["RLIM"]] >> qx
        sup.track_counts = rl + (rl >> 2)
        for i in _DERIVED:
            self._apply_param(i)

    def _apply_param(self, i):
        # what one parameter derives (param_set: only that one, a bounded piece of work)
        p = self.params
        sup = self.sup
        if i == T.P_TILT_LIMIT:
            sup.tilt_counts = self._counts_from_mrad(p[i])
        elif i == T.P_ARM_TILT:
            sup.arm_counts = self._counts_from_mrad(p[i])
        elif i == T.P_WATCHDOG_MS:
            sup.wd_ticks = (p[i] * self.rate) // 1000
        elif i == T.P_MAX_DUTY:
            self.motor.max_duty = p[i]
        elif i == T.P_POT_OFFSET:
            # calibration (upright board calibrate): pot offset (-1: the table's) and signs
            po = p[i]
            self.sensors.pot_offset = po if po >= 0 else self.table[self.off["CAL"]]
        elif i == T.P_ADC_SIGN:
            self.sensors.adc_sign = -1 if p[i] < 0 else 1
        elif i == T.P_ENC_SIGN:
            self.sensors.enc_sign = -1 if p[i] < 0 else 1
        elif i == T.P_MOTOR_SIGN:
            self._msign = -1 if p[i] < 0 else 1
            if self._hal_motor is not None:  # (None until __init__ binds the motor output)
                self._set_motor = self._hal_motor if self._msign > 0 else self._motor_neg
        elif i == T.P_GEAR_PLAY:
            # the predictor's gap model and half the play in x LSB (the controller's wheel side)
            g = p[i]
            h = (g << self.table[self.off["FMT"]]) >> 1
            ghb = self._gap_ticks(h)
            lim = self.ctrl.lim
            lim[LIM_GHB] = ghb
            lim[LIM_HPX] = h
            # the duty's sign for the gap model (Motor.duty's KDU u + KDV vh)
            mo = self.motor
            lim[LIM_KDU] = mo.kdu
            lim[LIM_KDV] = mo.kdv if mo.backemf else 0
            # the controller finds the wheel side from the gap model; the sensors' play operator
            # only where there is no gap model (a drive without its back-EMF constants)
            self.sensors.play = 0 if ghb else g >> 1
        elif i == T.P_CART_COULOMB:
            # the predictor's force while the motor side is in the play (controller LIM_FC)
            fc = self._force_u(p[i])
            self.ctrl.lim[LIM_FC] = fc
            # and the part of it the table's deadband compensation carries (the gap model's)
            self.ctrl.lim[LIM_FCC] = (fc >> 5) * FC_COMP + (((fc & 31) * FC_COMP) >> 5)

    def param_get(self, index):
        # the value, or 0 for an index out of range (the dispatcher checks first)
        if index < 0 or index >= T.N_PARAMS:
            return 0
        return self.params[index]

    def param_set(self, index, value):
        if index < 0 or index >= T.N_PARAMS:
            return T.R_BAD_INDEX
        p = T.PARAMS[index]
        if value < p[3] or value > p[4]:
            return T.R_OUT_OF_RANGE
        if index == T.P_LOOP_RATE:
            # the period is the active table's RATE, nothing else
            return T.R_READ_ONLY
        st = self.sup.state
        if (st == ARMED or st == BALANCING) and index in T.DRIVE_PARAMS:
            # signs, offsets, the drive: changed under a balancing robot they tip it
            return T.R_ARMED
        self.params[index] = value
        self._apply_param(index)
        return T.OK

    def _x_lsb(self, um):
        # a cart position (um) in the active table's x LSB, rounded (its REF scale)
        o = self.off["REF"]
        t = self.table
        return (um * t[o] + (t[o + 1] >> 1)) // t[o + 1]

    def cmd_set_reference(self, x_um):
        # a set-point is the controlling host's stream: it feeds the link watchdog
        self.sup.feed()
        lim = self.params[T.P_REF_LIMIT]
        if x_um > lim or x_um < -lim:
            return T.R_OUT_OF_RANGE
        r = fixmath.clamp(self._x_lsb(x_um), self.table[self.off["RLIM"]])
        st = self.params[T.P_REF_RATE]
        c = self.ctrl
        if st and self.sup.state == BALANCING and not c.catching:
            # ref_rate_mm_s: the controller's reference moves to r by st x LSB a tick (its ramp,
            # which Controller.schedule runs; from where a ramp under way has got to), at least 1.
            # The ramp's speed stays the controller's: a later catch's hand-back returns at it too
            # (a Controller attribute for the table's own RSTEP tipped the emulated board's timing)
            st = self._x_lsb((st * 1000) // self.rate)
            if st < 1:
                st = 1
            if not c.ramp:
                c.rr = self.ref
            c.rstep = st
            c.ramp = c.rr != r
        self.ref = r
        self.ref_um = x_um
        return T.OK
