# The firmware application: one control loop object, the protocol's target.
#
#   app = App(hal, link=None, gains=None, config=None)
#     hal     read_angle_raw() -> ADC counts, read_encoder() -> 16-bit counter,
#             set_motor(duty) (int, -32767..32767), ticks_us() (wraps at a multiple of 2**30).
#             If the HAL counts host frames in an attribute n_sensor (hal_hil.HilHal),
#             every new frame feeds the command watchdog.
#     link    optional object with poll(): called once per tick after the control step by
#             run() (serve the host link: decode commands, send telemetry); or set_link(link).
#     gains   optional gain module/object with LAYOUT and FLAT (default firmware.gains).
#     config  optional dict: pot_offset (ADC counts upright), adc_sign/enc_sign (+-1),
#             deadband (duty counts), backemf (bool), boot (int), stall_ms/stall_duty
#             (no-motion check, F_STALL; on by default: 100 ms at |duty| >= 2000;
#             stall_ms=0 switches it off), emitter ("bytecode",
#             "native" or "viper": how the controller step is compiled), and any msgtable PARAMS
#             name (e.g. watchdog_ms) -- config values are not range-checked, so
#             watchdog_ms=0 switches the watchdog off (bench/tests only).
#   app.step()   one control tick (allocation-free): read sensors, supervise, estimate,
#                control, drive the motor.  Returns the duty.
#   app.run(n=0, lock=True)  pace step() and the link's poll() at the loop rate with the
#                HAL's ticks (n steps, 0 = forever), the heap locked (micropython.heap_lock()
#                where the port has it; lock=False: tests on a port where locking misbehaves).
#                An allocation in the loop then raises MemoryError: it is caught, latched as
#                F_LOOP (fault, motor off) and the loop goes on.  Locked, MicroPython also
#                puts a large call frame (Controller.step's) on the C stack instead of
#                allocating and freeing it on the heap at every call.
#
# Target methods for firmware/commands.py return msgtable.OK or a reason code.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

try:
    from micropython import heap_lock as _heap_lock, heap_unlock as _heap_unlock
except ImportError:  # CPython, or a port without them
    _heap_lock = None
    _heap_unlock = None

from array import array

from . import fixmath
from . import msgtable as T
from .controller import Controller
from .motor import Motor
from .sensors import Sensors
from .supervisor import BALANCING, DISARMED, FAULT, F_GAINS, F_LOOP, Supervisor
from .timing import Timing

STALL_MS = const(100)  # no-motion check (F_STALL) default: this long without a count
STALL_DUTY = const(800)  # ... at |duty| at least this
_I16 = const(32767)
_U16 = const(65535)


class App:
    def __init__(self, hal, link=None, gains=None, config=None):
        if gains is None:
            from . import gains as _g
            gains = _g
        cfg = config if config is not None else {}
        self.hal = hal
        self.set_link(link)
        self.version = gains.VERSION
        layout = gains.LAYOUT
        flat = gains.FLAT
        self.ctrl = Controller(layout, flat)
        # the controller step: bytecode, or the native/viper builds of firmware/fastpath.py
        em = cfg.get("emitter", "bytecode")
        if em == "native":
            from .fastpath import step_native as cstep
        elif em == "viper":
            from .fastpath import step_viper as cstep
        else:
            cstep = Controller.step
        self._cstep = cstep
        off = self.ctrl.off
        self.off = off
        self.table = array("i", flat)
        self.rate = flat[off["RATE"]]
        self.sensors = Sensors(flat, off, cfg.get("adc_sign", 1), cfg.get("enc_sign", 1), cfg.get("pot_offset"))
        self.motor = Motor(flat, off, cfg.get("deadband"), cfg.get("backemf", True))
        self.sup = Supervisor()
        self.timing = Timing(1000000 // self.rate)
        self.boot = cfg.get("boot", 0) & 0xFF
        self.ref = 0
        self.ref_um = 0
        self.duty = 0
        self.tick = 0
        self.uptime_ms = 0
        self._us_frac = 0
        self.step_us = 0
        self.gains_crc = 0
        self._frames = -1
        self._has_frames = hasattr(hal, "n_sensor")
        # parameters: defaults from msgtable, then config overrides by name
        self.params = array("i", [0] * T.N_PARAMS)
        for p in T.PARAMS:
            self.params[p[0]] = p[5]
        for p in T.PARAMS:
            if p[1] in cfg:
                self.params[p[0]] = cfg[p[1]]
        self.params[T.P_LOOP_RATE] = cfg.get("loop_rate_hz", self.rate)
        self._apply_params()
        # no-motion check (F_STALL): |duty| >= stall_duty for stall_ms without one encoder
        # count (stall_ms=0: off).  800 duty (~2 N at rest, 3/4 of the default design's
        # force clamp) for 100 ms moves the cart by centimetres
        self.sup.stall_ticks = (cfg.get("stall_ms", STALL_MS) * self.rate) // 1000
        self.sup.stall_duty = cfg.get("stall_duty", STALL_DUTY)
        # a table the firmware's own check rejects is latched as a fault
        if self.ctrl.validate(self.table, len(self.table), self.version) != T.OK:
            self.sup.faults |= F_GAINS
            self.sup.state = FAULT
        # bound methods cached for the loop
        self._step = self.step
        self._read_adc = hal.read_angle_raw
        self._read_enc = hal.read_encoder
        self._set_motor = hal.set_motor
        self._ticks = hal.ticks_us

    # ---- parameters -> derived integers (outside the loop) ----
    def _counts_from_mrad(self, mrad):
        o = self.off["TILT"]
        t = self.table
        return (mrad * t[o] + (1 << (t[o + 1] - 1))) >> t[o + 1]

    def _apply_params(self):
        p = self.params
        sup = self.sup
        sup.tilt_counts = self._counts_from_mrad(p[T.P_TILT_LIMIT])
        sup.arm_counts = self._counts_from_mrad(p[T.P_ARM_TILT])
        rate = p[T.P_LOOP_RATE]
        if rate <= 0:
            rate = self.rate
        sup.wd_ticks = (p[T.P_WATCHDOG_MS] * rate) // 1000
        t = self.table
        # track fault at 1.25 x the reference limit (encoder counts)
        qx = t[self.off["FMT"]]
        rl = t[self.off["RLIM"]] >> qx
        sup.track_counts = rl + (rl >> 2)
        self.motor.max_duty = p[T.P_MAX_DUTY]
        self.period_us = 1000000 // rate
        self.timing.period_us = self.period_us

    # ---- the loop ----
    def step(self):
        t0 = self._ticks()
        tm = self.timing
        tm.begin(t0)
        s = self.sensors
        s.update(self._read_adc(), self._read_enc())
        sup = self.sup
        if self._has_frames:
            n = self.hal.n_sensor
            if n != self._frames:
                self._frames = n
                sup.wd_count = 0
        start = sup.update(s.counts, s.pos, s.rail, s.jump, s.delta, self.duty)
        duty = 0
        if sup.state == BALANCING:
            c = self.ctrl
            if start:
                s.zero()
                c.reset(s.yx, s.yp)
            u = self._cstep(c, s.yx, s.yp, self.ref)
            duty = self.motor.duty(u, c.vh)
        self._set_motor(duty)
        self.duty = duty
        # counters wrap at 2**30 without computing it (not a small int on 32 bits)
        self.tick = fixmath.ticks_next(self.tick)
        f = self._us_frac + self.period_us
        while f >= 1000:
            f -= 1000
            self.uptime_ms = fixmath.ticks_next(self.uptime_ms)
        self._us_frac = f
        self.step_us = tm.end(t0, self._ticks())
        return duty

    def set_link(self, link):
        # attach the host link (an object with poll()); its bound method is cached here
        # so that run() allocates nothing
        self.link = link
        self._poll = link.poll if link is not None else None

    def run(self, n=0, lock=True):
        # real-time mode: one step (and the link's poll) every period_us, busy-waiting on
        # the HAL clock; a late tick starts the next period from now (no catch-up burst)
        ticks = self._ticks
        diff = fixmath.ticks_diff
        add = fixmath.ticks_add
        step = self._step
        poll = self._poll
        locked = lock and _heap_lock is not None
        k = 0
        deadline = ticks()
        if locked:
            _heap_lock()
        try:
            while n == 0 or k < n:
                while diff(deadline, ticks()) > 0:
                    pass
                try:
                    step()
                    if poll is not None:
                        poll()
                except MemoryError:
                    self._loop_fault()
                deadline = add(deadline, self.period_us)
                if diff(ticks(), deadline) > self.period_us:
                    deadline = ticks()
                if n:
                    # counted only when bounded: forever, k would outgrow a small int
                    k += 1
        finally:
            if locked:
                _heap_unlock()

    def _loop_fault(self):
        # the loop could not complete a tick (see run()): latch, motor off
        sup = self.sup
        sup.faults |= F_LOOP
        sup.state = FAULT
        self._set_motor(0)
        self.duty = 0

    # ---- target of firmware/commands.py ----
    def feed_watchdog(self):
        self.sup.feed()

    def cmd_arm(self):
        self.sup.feed()
        return self.sup.arm()

    def cmd_disarm(self):
        self.sup.feed()
        r = self.sup.disarm()
        self._set_motor(0)
        self.duty = 0
        return r

    def cmd_clear_faults(self):
        self.sup.feed()
        return self.sup.clear()

    def cmd_set_reference(self, x_um):
        self.sup.feed()
        lim = self.params[T.P_REF_LIMIT]
        if x_um > lim or x_um < -lim:
            return T.R_OUT_OF_RANGE
        o = self.off["REF"]
        t = self.table
        r = (x_um * t[o] + (t[o + 1] >> 1)) // t[o + 1]
        self.ref = fixmath.clamp(r, t[self.off["RLIM"]])
        self.ref_um = x_um
        return T.OK

    def param_get(self, index):
        # the value, or 0 for an index out of range (the dispatcher checks first)
        if index < 0 or index >= T.N_PARAMS:
            return 0
        return self.params[index]

    def param_set(self, index, value):
        self.sup.feed()
        if index < 0 or index >= T.N_PARAMS:
            return T.R_BAD_INDEX
        p = T.PARAMS[index]
        if value < p[3] or value > p[4]:
            return T.R_OUT_OF_RANGE
        if index == T.P_LOOP_RATE and self.sup.state != DISARMED and self.sup.state != FAULT:
            return T.R_ARMED
        self.params[index] = value
        self._apply_params()
        return T.OK

    def gains_apply(self, buf, nbytes):
        # a complete, CRC-checked table from the dispatcher: int32 little-endian in
        # the layout of firmware/gains.py; re-checked here before it replaces the live one
        self.sup.feed()
        if self.sup.state != DISARMED and self.sup.state != FAULT:
            return T.R_ARMED
        n = nbytes >> 2
        if nbytes & 3 or n != self.ctrl.length:
            return T.R_BAD_LENGTH
        sc = self.ctrl.scratch
        for i in range(n):
            v = fixmath.s32_le(buf, 4 * i)
            if v is None:
                return T.R_UNSTABLE
            sc[i] = v
        r = self.ctrl.validate(sc, n, self.version)
        if r != T.OK:
            return r
        t = self.table
        for i in range(n):
            t[i] = sc[i]
        off = self.off
        self.ctrl.load(t)
        self.sensors.load(t, off)
        self.motor.load(t, off)
        self.rate = t[off["RATE"]]
        self._apply_params()
        self.sup.faults &= ~F_GAINS
        return T.OK

    def fill_heartbeat(self, arr):
        arr[0] = self.sup.state
        arr[1] = self.sup.faults
        arr[2] = self.boot
        arr[3] = self.uptime_ms

    def _tel(self, v, j):
        t = self.table
        o = self.off["TEL"]
        s = t[o + 5]
        v = (v * t[o + j] + (1 << (s - 1))) >> s
        if v > _I16:
            return _I16
        if v < -_I16:
            return -_I16
        return v

    def fill_telemetry(self, arr):
        # TELEM_STATE (x, xdot, phi, phidot: filtered estimate) then TELEM_CTRL
        # (ref, force, duty, step_us), in the message units
        xf = self.ctrl.xf
        arr[0] = self._tel(xf[0], 0)
        arr[1] = self._tel(self.ctrl.vh, 1)
        arr[2] = self._tel(xf[2], 2)
        arr[3] = self._tel(xf[3], 3)
        arr[4] = self._tel(self.ref, 0)
        arr[5] = self._tel(self.ctrl.u, 4)
        arr[6] = self.duty
        arr[7] = self.step_us if self.step_us < _U16 else _U16

    def fill_timing(self, arr):
        # TIMING fields since the last report, then a new interval starts
        tm = self.timing
        arr[0] = tm.step_min if tm.steps else 0
        arr[1] = tm.step_max
        arr[2] = tm.period_max if tm.period_max < _U16 else _U16
        arr[3] = tm.overruns
        tm.reset()
