# The firmware application: one control loop object, the protocol's target.
#
#   app = App(hal, link=None, gains=None, config=None)
#     hal     a firmware.hal_base.Hal: read_angle_raw() -> ADC counts, read_encoder() -> 16-bit
#             counter, set_motor(duty) (int, -32767..32767), ticks_us() (wraps at a multiple
#             of 2**30), and the optional capabilities declared there (None: absent), read once
#             here: n_sensor (host frames, hal_hil.HilHal: each new one feeds the command
#             watchdog), read_supply_mv() (the duty scaled by nominal/measured, F_UNDERVOLT),
#             adc_open (True: the wiper test found the angle potentiometer open -> F_ADC_OPEN).
#     link    optional object with poll(): called once per tick after the control step by
#             run() (serve the host link: decode commands, send telemetry); or set_link(link).
#     gains   optional gain module/object with LAYOUT, FLAT and CRC (default firmware.gains).
#     config  optional dict: the keys of firmware/appconfig.py CONFIG (default, range,
#             meaning; cfg_value: an unknown key or a value out of range -> ValueError naming
#             it) and msgtable PARAMS names (the parameters' start values; the DRIVE_PARAMS
#             ones range-checked, the others not: watchdog_ms=0 switches the watchdog off,
#             bench/tests only).  The no-motion check (F_STALL): appconfig STALL_MS, STALL_DUTY.
#   app.attach_store(store)  at start-up: load the newest valid saved configuration
#                (firmware/store.py); copies there but none valid -> defaults, F_CONFIG.
#   SAVE_CONFIG (cmd_save) is queued and run by service_save() between ticks, motor off.
#     Optional HAL methods (hal_base.Hal), each used only when not None: set_enable(on)
#     (driver enable: high only while balancing), estop() (True while the e-stop input is
#     asserted or was since the last call -> F_ESTOP), wdt_start(ms)/wdt_feed()/wdt_stop()
#     (hardware watchdog: started by run() when config wdt_ms > 0, fed once per completed
#     tick, by nothing else), mark(cause) (the reset cause to report if the board resets
#     now: msgtable.RC_*; see firmware/main.py), set_period(us).
#   Timing is a safety input: the period is always the active gain table's RATE
#   (loop_rate_hz is read-only); run() checks the time between step starts every tick:
#   a gap > 1.5 periods is a late tick; while armed/balancing F_DEADLINE latches on one gap
#   > _GAP_PERIODS periods, or when the late-tick budget runs out (each late tick adds
#   _LATE_W to a score that each on-time tick lowers by 1; over _LATE_MAX: more than 4 late
#   ticks in a row, or more than 1 in 26 sustained).  Balancing starts only once run() has
#   seen _WARMUP on-time periods (supervisor.timing_ok).  Readiness (supervisor.ready): the
#   active table passed validate() and its CRC (the flashed table: gains.CRC, at boot).
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

from . import crc16
from .appparams import Params
from .appstatus import Reports
from .appstore import ConfigSave
from .apptable import TableUpload
from .commands import Target
from . import emitter
from . import fixmath
from . import msgtable as T
from .appconfig import cfg_check, cfg_params, cfg_value, epoch0
from .controller import Controller
from .excite import EXC_OPEN, Excite
from .supervisor import ARMED, BALANCING, DISARMED, FAULT, F_ADC_OPEN, F_CONFIG, F_GAINS, F_LOOP, F_UNDERVOLT
from .supervisor import F_DEADLINE, F_ESTOP, F_RESET

# deadline rule (F_DEADLINE, see above) and timing readiness
_LATE_W = const(25)
_LATE_MAX = const(100)
_GAP_PERIODS = const(10)
_WARMUP = const(16)
# hardware watchdog timeout while a queued configuration save writes the flash (motor off)
_SAVE_WDT_MS = const(5000)
_I16 = const(32767)
_U16 = const(65535)
_TICKS_MASK = const(0x3FFFFFFF)  # tick/uptime counters wrap to 0 after this (fixmath)
# the arming token's generator (App._new_token): a = 0x41C64E6D mod 2**30 in 15-bit limbs, c
_LCG_AL = const(0x4E6D)
_LCG_AH = const(0x038C)
_LCG_C = const(12345)


class App(Reports, Params, TableUpload, ConfigSave, Target):
    # the parts, each its own module: Reports (appstatus.py: heartbeat, status, stats,
    # timing, version, session replies), Params (appparams.py: parameters and set-point),
    # TableUpload (apptable.py: the gain table), ConfigSave (appstore.py: the saved
    # configuration); Target (commands.py: the optional capabilities' None defaults) last,
    # so a part's method is found before Target's None
    _hal_motor = None  # the HAL's set_motor, bound in __init__ after the parameters are applied

    def __init__(self, hal, link=None, gains=None, config=None):
        if gains is None:
            from . import gains as _g
            gains = _g
        cfg = config if config is not None else {}
        cfg_check(cfg)
        self.hal = hal
        self.set_link(link)
        self.version = gains.VERSION
        layout = gains.LAYOUT
        flat = gains.FLAT
        self.ctrl = Controller(layout, flat)
        # the code emitter of every hot part (firmware/emitter.py: the one place that chooses)
        em = emitter.check(cfg_value(cfg, "emitter"))
        Sn, Mo, Su, Tm, self._cstep = emitter.parts(em)
        self.emitter = em  # also the host link's (framing.Encoder, the pacer, the commands' CRC)
        off = self.ctrl.off
        self.off = off
        # telemetry scaling (fill_telemetry): the TEL offset, and viper's build of it
        self._tel_o = off["TEL"]
        self._tel_fast = emitter.telemetry(em)
        self.table = array("i", flat)
        self.rate = flat[off["RATE"]]
        # the sensors' offset and signs are parameters (_apply_params sets them)
        self.sensors = Sn(flat, off)
        self.motor = Mo(flat, off, cfg_value(cfg, "deadband"), cfg_value(cfg, "backemf"))
        self.sup = Su()
        # identification excitation (EXCITE; firmware/excite.py)
        self.exc = Excite()
        # tick arithmetic: the HAL's own where it has it (HalPico: time.ticks_diff/add, C)
        self._tdiff = hal.ticks_diff_fast or fixmath.ticks_diff
        self._tadd = hal.ticks_add_fast or fixmath.ticks_add
        self.timing = Tm(1000000 // self.rate, self._tdiff)
        self.boot = cfg_value(cfg, "boot") & 0xFF
        self.ref = 0
        self.ref_um = 0
        self.duty = 0
        self.tick = 0
        self.uptime_ms = cfg_value(cfg, "uptime_ms") & _TICKS_MASK
        self._us_frac = 0
        self.step_us = 0
        self.gains_crc = 0
        self._crc_table = crc16.make_table()
        # hardware cut-offs: driver enable, e-stop input, hardware watchdog, reset marker
        self._set_enable = hal.set_enable
        self._estop = hal.estop
        # (flags, not bound methods: reading hal.wdt_start would allocate one in run())
        self._has_wdt = hal.wdt_start is not None
        self._has_period = hal.set_period is not None
        self._en = 1
        self.wdt_ms = cfg_value(cfg, "wdt_ms")
        self._wdt_feed = None
        self.reset_cause = cfg_value(cfg, "reset_cause")
        # deadline check (run()): late-tick score, counts, pending flags for the next step
        self.deadline_check = cfg_value(cfg, "deadline")
        self.late_score = 0
        self.n_late = 0
        self._on_time = 0
        # the last step guard_tick ran for the link's user hook: its deadline and start (run())
        self._gdl = 0
        self._glast = 0
        self._ext = 0
        # arming epoch (HEARTBEAT.epoch; ARM must carry it): changes on every disarm,
        # clear_faults and entry into FAULT (step() watches the state)
        self.epoch = epoch0(cfg, self.boot)
        self._st = -1
        # heap statistics (STATS_LOOP): gc.mem_free()/mem_alloc() walk the heap (~9 ms each
        # on a Pico), so they are sampled only outside the control tick -- at start-up, when
        # run() starts, after a save, and between ticks after a stats request while the
        # motor is off (App.run) -- and the reply reports the last sample
        self._gc_count = 0
        self._alloc_last = 0
        self.heap_free = 0
        self._heap_due = False
        self.sample_heap()
        # persistent configuration (attach_store) and a queued save (cmd_save)
        self.store = None
        self.config_bad = False
        self.save_seq = -1
        self._save_disp = None
        self.n_saves = 0
        self.cfg_status = 3  # msgtable S_CFG_STATUS: no storage (attach_store: what it loaded)
        # loop starts since the board started (main.py: +1 after a MODE switch back) and the
        # board time at this start (config uptime_ms: main.py carries it across the switch)
        self.starts = cfg_value(cfg, "starts")
        # motor supply (HAL read_supply_mv) and the angle wiper test (HAL adc_open)
        self._read_vsup = hal.read_supply_mv
        self._has_open = hal.adc_open is not None
        self.vsup_nom = cfg_value(cfg, "vsup_nom_mv")
        self.vsup_min = cfg_value(cfg, "vsup_min_mv")
        self.vsup_mv = self.vsup_nom
        self._vsup_acc = -1
        if self._read_vsup is not None:
            self._supply = emitter.supply(self)
        self._frames = -1
        self._has_frames = hal.n_sensor is not None
        # parameters: defaults from msgtable, then config overrides by name
        self.params = array("i", [0] * T.N_PARAMS)
        cfg_params(cfg, self.params)
        self.params[T.P_LOOP_RATE] = self.rate
        # no-motion check (F_STALL): |duty| >= stall_duty for stall_ms without one encoder
        # count (stall_ms=0: off).  The defaults (appconfig STALL_DUTY for STALL_MS) move a
        # free cart by centimetres; in ticks at the active table's rate (_apply_params: again
        # whenever the table changes)
        # (beyond the table's deadband compensation, which every nonzero force adds and which
        # moves nothing on a bridge with that deadband: _apply_params)
        self.stall_ms = cfg_value(cfg, "stall_ms")
        self.stall_duty = cfg_value(cfg, "stall_duty")
        self._apply_params()
        # readiness of the flashed table: the firmware's own check and its CRC (gains.CRC);
        # a table that fails either is never run (F_GAINS on every tick, arm refused)
        n = len(self.table)
        self.gains_crc = self._table_crc(self.table, n)
        ok = self.ctrl.validate(self.table, n, self.version) == T.OK
        self.sup.ready = ok and self.gains_crc == gains.CRC
        if not self.sup.ready:
            self.sup.faults |= F_GAINS
            self.sup.state = FAULT
        latch = self.reset_cause
        # VERSION.reset_cause: why the board last reset, also after a MODE switch restarted the
        # loop (main.py: config reset_cause_boot; F_RESET latches on the first start only)
        rb = cfg_value(cfg, "reset_cause_boot")
        self.reset_cause = latch if rb is None else rb
        if latch != T.RC_POWER_ON:
            # restarted by the hardware watchdog or a loop exception: the host must see it
            self.sup.faults |= F_RESET
            self.sup.state = FAULT
        # bound methods cached for the loop
        # the step of the emitter (viper: fasttick.StepV, whose bound method then hides App.step)
        if em == "viper":
            self.step = emitter.step(self)
        self._step = self.step
        self._period_m = self._period
        self._read_adc = hal.read_angle_raw
        self._read_enc = hal.read_encoder
        self._hal_motor = hal.set_motor
        self._motor_neg = self._set_motor_neg
        self._set_motor = hal.set_motor if self._msign > 0 else self._motor_neg
        self._ticks = hal.ticks_us  # with _tdiff and emitter: read by the links (link_serial, admit)
        self._drive(0)

    # ---- the loop ----
    def step(self):
        ticks = self._ticks
        t0 = ticks()
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
        ext = self._ext
        if ext:
            self._ext = 0
        if self._estop is not None and self._estop():
            ext |= F_ESTOP
        if self._has_open and self.hal.adc_open:
            ext |= F_ADC_OPEN
        if self._read_vsup is not None:
            ext |= self._supply(sup.state)
        start = sup.update(s.counts, s.pos, s.rail, s.jump, s.delta, self.duty, ext)
        st = sup.state
        if st != self._st:
            if st == FAULT:
                self._new_token()
            self._st = st
        duty = 0
        if sup.state == BALANCING:
            c = self.ctrl
            if start:
                s.zero()
                c.reset(s.yx, s.yp)
            # catch mode for large tilts (a compare, a row swap; the reference it returns
            # differs from self.ref only while handing back).  Controller.schedule's common
            # case -- not catching, no ramp, the prediction inside phi_on: the reference as
            # set -- is checked here without the call (a call costs more on a board)
            r = self.ref
            if c.catching or c.ramp:
                r = c.schedule(r)
            else:
                on = c.phi_on
                if on > 0 and (c.p[2] > on or c.p[2] < -on):
                    r = c.schedule(r)
            u = self._cstep(c, s.yx, s.yp, r)
            duty = self.motor.duty(u, c.vh)
            if self.exc.on:
                duty = self._excite(c, u)
            # the driver is enabled only while balancing, before the first duty
            if not self._en:
                self._drive(1)
            self._set_motor(duty)
        else:
            self._set_motor(0)
            if self._en:
                self._drive(0)
            # disarm or fault: the excitation stops (the telemetry keeps its mode)
            self.exc.on = 0
        self.duty = duty
        # counters wrap at 2**30 without computing it (not a small int on 32 bits)
        # (fixmath.ticks_next inlined: a call costs more than this on a board)
        k = self.tick
        self.tick = k + 1 if k < _TICKS_MASK else 0
        f = self._us_frac + self.period_us
        if f >= 1000:
            k = self.uptime_ms
            while f >= 1000:
                f -= 1000
                k = k + 1 if k < _TICKS_MASK else 0
            self.uptime_ms = k
        self._us_frac = f
        self.step_us = tm.end(t0, ticks())
        return duty

    def _excite(self, c, u):
        # the excitation on the force (mode 1: added, clamped, stored for the predictor;
        # mode 2: alone, no back-EMF compensation); telemetry's force shows what was applied
        ex = self.exc
        e = ex.next()
        if ex.mode == EXC_OPEN:
            u = e
            vh = 0
        else:
            u = fixmath.clamp(u + e, c.ulim)
            if c.d > 0:
                c.b[c.d - 1] = u
            vh = c.vh
        c.u = u
        return self.motor.duty(u, vh)

    def cmd_excite(self, mode, amp_mn, div):
        # EXCITE: start (only while balancing) or stop the identification excitation
        if mode != 0 and self.sup.state != BALANCING:
            return T.R_BAD_STATE
        return self.exc.start(mode, amp_mn, div, self.table[self.off["FMT"] + 4], self.ctrl.ulim)

    def _supply(self, st):
        # the motor supply: filtered (8 ticks), scales the duty; returns F_UNDERVOLT when it
        # is below vsup_min_mv while armed or balancing
        v = self._read_vsup()
        a = self._vsup_acc
        if a < 0:
            a = v << 3
        else:
            a += v - (a >> 3)
        self._vsup_acc = a
        v = a >> 3
        if v != self.vsup_mv:
            self.vsup_mv = v
            self.motor.set_supply(v, self.vsup_nom)
        if v < self.vsup_min and (st == ARMED or st == BALANCING):
            return F_UNDERVOLT
        return 0

    def set_link(self, link):
        # attach the host link (an object with poll()); its bound method is cached here
        # so that run() allocates nothing
        self.link = link
        self._poll = link.poll if link is not None else None

    def run(self, n=0, lock=True):
        # real-time mode: one step (and the link's poll) every period_us, busy-waiting on
        # the HAL clock; a late tick starts the next period from now (no catch-up burst)
        ticks = self._ticks
        diff = self._tdiff
        add = self._tadd
        step = self._step
        poll = self._poll
        locked = lock and _heap_lock is not None
        k = 0
        # self-paced: the period must be measured before balancing; the hardware watchdog
        # (config wdt_ms) runs from here on, fed once per completed tick and by nothing else
        self.sup.timing_ok = False
        self._on_time = 0
        self.late_score = 0
        self.sample_heap()
        self._wdt_start(self.wdt_ms)
        feed = self._wdt_feed
        period = self._period_m
        sup = self.sup
        deadline = ticks()
        last = deadline
        first = True
        if locked:
            _heap_lock()
        try:
            while n == 0 or k < n:
                while diff(deadline, ticks()) > 0:
                    pass
                now = ticks()
                if first:
                    first = False
                else:
                    per = diff(now, last)
                    p = self.period_us
                    # _period() has nothing to do for an on-time tick with no late score once
                    # the period is measured: that common case skips the call (board: ~40 us)
                    if per > p + (p >> 1) or self.late_score or not sup.timing_ok:
                        period(per)
                last = now
                try:
                    step()
                    if poll is not None and poll():
                        # the link's user hook ran past deadlines and its guard ran those steps
                        # on time (guard_tick): the schedule goes on from the last of them
                        deadline = self._gdl
                        last = self._glast
                except MemoryError:
                    self._loop_fault()
                if feed is not None:
                    feed()
                if self.save_seq >= 0:
                    # a queued save (motor off): between ticks, heap unlocked; pacing restarts
                    # (the watchdog window is widened for the flash writes, the gap not timed)
                    self._wdt_window(_SAVE_WDT_MS, locked)
                    self.service_save(locked)
                    self._wdt_window(self.wdt_ms, locked)
                    self._paused()
                    deadline = ticks()
                    first = True
                elif self._heap_due and (sup.state == DISARMED or sup.state == FAULT):
                    # heap statistics asked for (fill_stats) with the motor off: sampled
                    # between ticks (a heap walk, ~18 ms on a Pico), pacing restarts
                    self._paused()
                    deadline = ticks()
                    first = True
                deadline = add(deadline, self.period_us)
                if diff(ticks(), deadline) > self.period_us:
                    deadline = ticks()
                if n:
                    # counted only when bounded: forever, k would outgrow a small int
                    k += 1
        finally:
            if locked:
                _heap_unlock()
        # a bounded run (tests, bench) ends cleanly: the watchdog stops with it.  An
        # exception leaves it running (main.py resets the board; a hang is reset by it)
        if self._wdt_feed is not None:
            self.hal.wdt_stop()
            self._wdt_feed = None
            self._mark(T.RC_POWER_ON)

    def _period(self, per):
        # run(), every tick: per = us between this step start and the previous one
        p = self.period_us
        sup = self.sup
        if per <= p + (p >> 1):
            if self.late_score > 0:
                self.late_score -= 1
            if not sup.timing_ok:
                self._on_time += 1
                if self._on_time >= _WARMUP:
                    sup.timing_ok = True
            return
        if self.n_late < _U16:
            self.n_late += 1
        self._on_time = 0
        st = sup.state
        if st != ARMED and st != BALANCING:
            # motor off: nothing to cut, but the period is measured again before balancing
            sup.timing_ok = False
            self.late_score = 0
            return
        s = self.late_score + _LATE_W
        if per > p * _GAP_PERIODS:
            s = _LATE_MAX + 1
        if s > _LATE_MAX:
            s = 0
            if self.deadline_check:
                sup.timing_ok = False
                self._ext |= F_DEADLINE
        self.late_score = s

    def _drive(self, on):
        # driver enable (HAL set_enable, when it has one); on: 0 or 1
        self._en = on
        if self._set_enable is not None:
            self._set_enable(on)

    def _mark(self, cause):
        m = self.hal.mark
        if m is not None:
            m(cause)

    def _wdt_start(self, ms):
        # start the hardware watchdog (and mark: a reset from now on is the watchdog's)
        if ms > 0 and self._has_wdt:
            self.hal.wdt_start(ms)
            self._wdt_feed = self.hal.wdt_feed
            self._mark(T.RC_WATCHDOG)

    def _wdt_window(self, ms, locked):
        # change a running watchdog's timeout (outside the tick; machine.WDT may allocate)
        if self._wdt_feed is None or ms <= 0:
            return
        if locked:
            _heap_unlock()
        try:
            self.hal.wdt_start(ms)
        finally:
            if locked:
                _heap_lock()

    def guard_tick(self, dl):
        # one tick on time while the link's user hook runs (admit.Admit.take: its guard timer's
        # callback at the deadline dl): what run()'s loop does for a tick but the link -- the
        # step, a loop fault on an allocation, the watchdog fed; run() goes on from it
        self._glast = self._ticks()
        self._gdl = dl
        try:
            self._step()
        except MemoryError:
            self._loop_fault()
        f = self._wdt_feed
        if f is not None:
            f()

    def _loop_fault(self):
        # the loop could not complete a tick (see run()): latch, motor off
        sup = self.sup
        sup.faults |= F_LOOP
        sup.state = FAULT
        self._set_motor(0)
        self._drive(0)
        self.duty = 0

    # ---- target of firmware/commands.py ----
    def feed_watchdog(self):
        self.sup.feed()

    def cmd_arm(self):
        # the dispatcher checked the epoch; arming (re)starts the watchdog count
        return self.sup.arm()

    def cmd_disarm(self):
        # every disarm draws a new token: no arm sent before it can act after it
        self._new_token()
        r = self.sup.disarm()
        self._set_motor(0)
        self._drive(0)
        self.duty = 0
        return r

    def cmd_clear_faults(self):
        r = self.sup.clear()
        if r == T.OK:
            self._new_token()
        if r == T.OK and self.config_bad:
            # no valid saved configuration: stays latched until a table is uploaded
            self.sup.faults |= F_CONFIG
            self.sup.state = FAULT
        return r

    def _set_motor_neg(self, duty):
        # motor_sign -1: the HAL gets the opposite duty (set_motor is this method then)
        self._hal_motor(-duty)

    def _paused(self):
        # after a pause of the loop between ticks (a save, a heap walk; motor off): the heap
        # sampled, the pause not timed as a period, the encoder's counts of the pause followed
        # (a rolling cart is not an encoder jump)
        self.sample_heap()
        self.timing.restart()
        self.sensors.follow(self._read_enc())

    def _new_token(self):
        # the next arming token (disarm, clear_faults, fault): x -> a*x + c mod 2**30, a = 1 mod
        # 4 and c odd (full period: no token repeats within 2**30 draws), in 15-bit limbs so
        # every intermediate is a small int on a 32-bit port; allocation-free (the tick calls it)
        x = self.epoch
        hi = x >> 15
        lo = x & 0x7FFF
        t = _LCG_AL * lo
        m = ((_LCG_AH * lo) & 0x7FFF) + ((_LCG_AL * hi) & 0x7FFF)
        s = (t & 0x7FFF) + _LCG_C
        self.epoch = ((((t >> 15) + m + (s >> 15)) & 0x7FFF) << 15) | (s & 0x7FFF)

    def _tel(self, v, j):
        t = self.table
        o = self._tel_o
        s = t[o + 5]
        v = (v * t[o + j] + (1 << (s - 1))) >> s
        if v > _I16:
            return _I16
        if v < -_I16:
            return -_I16
        return v

    def fill_telemetry(self, arr):
        # TELEM_STATE (x, xdot, phi, phidot: filtered estimate) then TELEM_CTRL
        # (ref, force, duty, step_us), in the message units (viper: one call, same values).
        # ref is the reference the controller tracks: the ramp's while one runs (set-point or
        # catch hand-back, Controller.schedule), else the set-point
        c = self.ctrl
        ref = c.rr if c.ramp else self.ref
        if self._tel_fast is not None:
            self._tel_fast(arr, self.table, c.xf, self._tel_o, c.vh, ref, c.u)
        else:
            xf = c.xf
            arr[0] = self._tel(xf[0], 0)
            arr[1] = self._tel(c.vh, 1)
            arr[2] = self._tel(xf[2], 2)
            arr[3] = self._tel(xf[3], 3)
            arr[4] = self._tel(ref, 0)
            arr[5] = self._tel(c.u, 4)
        if self.sup.state != BALANCING:
            # motor off (disarmed, armed waiting to catch, fault): the force is what is
            # applied (0), the state the sensors as read, at rest -- not the estimate of the
            # last balancing tick, which the controller no longer updates
            s = self.sensors
            arr[0] = self._tel(fixmath.clamp(s.yx, c.lim[0]), 0)
            arr[1] = 0
            arr[2] = self._tel(fixmath.clamp(s.yp, c.lim[2]), 2)
            arr[3] = 0
            arr[5] = 0
        elif self.exc.mode:
            # an excitation is set: x and phi as the sensors read them (upright identify)
            s = self.sensors
            arr[0] = self._tel(fixmath.clamp(s.yx, c.lim[0]), 0)
            arr[2] = self._tel(fixmath.clamp(s.yp, c.lim[2]), 2)
        arr[6] = self.duty
        arr[7] = self.step_us if self.step_us < _U16 else _U16

