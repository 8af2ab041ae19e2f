# The host links' admission rule in predicted time (issue 26), one copy for both links
# (link_serial.SerialLink, link_can.CanLink): a received frame is handled in this tick only when
# its planned cost still ends within the tick's limit, counted from the step's *scheduled* start
# (App: timing.last_us); what does not fit is held for the next tick.  The limit is the period
# for a frame read in this tick (plim) and app.link_budget_us (lim: 1.5 periods less what follows
# a frame before the next step, the larger of 1/8 period and REFILL_US) for one held from the last
# tick -- so a command too long to fit beside the step and its own reading
# is read in one tick and handled at the start of the next -- less what the last tick ran past
# its period (over: the next tick catches up).  A backlog held _FORCE ticks in a row gets one frame whatever the
# time (a loop rate at which no frame ever fits still answers, one late tick per FORCE ticks of
# traffic).  Then the user hook (set_user): called in the spare time left, timed, switched off
# when over its budget -- and, with a HAL guard timer (HalPico: machine.Timer, whose callback the
# rp2 port schedules from the alarm interrupt into the main thread's next bytecode), guarded:
# the timer is armed for the next step's deadline before the hook is called and cancelled when
# it returns; if the hook still runs then, the callback (take) runs that step and feeds the
# watchdog on time, again each period, and App.run goes on from the last of those steps.  A
# single C call in the hook longer than a period that serves no events (a blocking bus
# transfer; time.sleep_us does serve them) still delays the step: the callback waits for it.
#
#   a = Admit(app)           app: the App (its clock _ticks/_tdiff, timing, link_budget_us);
#                            a.on True (a host test may set it False: no rule)
#   a.open()                 a tick's receive phase starts: a.t0 (the step's scheduled start),
#                            a.lim, a.plim (us from t0 a frame must end within), a.force
#   the link, per frame:     c = a.ctab[mid] (a REQUEST: a.rtab[requested id & 31]) + its own;
#                            now = ticks_diff(ticks(), a.t0); the frame goes when
#                            now <= lim - c or (force and k == 0)   (k: frames handled so far)
#                            -- a.fits_now(c, k, fresh) in the CAN link; written inline in the
#                            serial link, with open()/close()'s statements too (a method call
#                            costs ~50 us on a predicted Pico from a cold cache, its planned
#                            costs were measured without any, and its request sweep saw a late
#                            tick with the calls)
#   a.fits_now(c, k, fresh) the same comparison as a call, the clock read in it (link_can)
#   a.close(now, k, backlog) the receive phase ends (now < 0: the clock is read); backlog:
#                            frames still waiting (held or unread)
#   a.over = 0               a tick with no receive phase (nothing came in): nothing carried
#   a.set_user(fn, us), a.user()   the user hook (after close/idle); user() returns the steps
#                            its guard ran (App.guard_tick: run() goes on from the last)
#
# The planned costs are measured on the predicted real Pico (the harness's XIP cache model, a
# cold cache: command code runs rarely) -- docs/firmware.md, "Board timing".  Allocation-free;
# integers only.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from array import array

from . import msgtable as T

# a frame's work on a predicted real Pico (us, XIP model, cold cache, measured with the telemetry
# pair every tick on the serial link): a host heartbeat 320; a stats request (three replies)
# 1530, a timing request 1283; every other frame at most ~1090 (arm 1090, excite 1080, param_set
# 1067, gains_chunk 1059, set_reference 979)
HB_US = const(400)
# what follows a frame until the next step starts, on a predicted real Pico: the loop's own code
# refilling the flash cache the frame's cold code evicted (traced: a param_set's receive phase
# closed 2699 us after its step's start and the next step began 466 us later, 3165 us between
# step starts -- a late tick -- where the budget then kept 1/8 period, 250 us at 500 Hz, for it).
# app.link_budget_us keeps at least this much before 1.5 periods (docs/firmware.md, "Board timing")
REFILL_US = const(500)
FRAME_US = const(1200)
HEAVY_US = const(1600)
FORCE = const(8)  # ticks a backlog waits at most before one frame goes whatever the time
_USER_MARGIN = const(100)  # us a user hook leaves before the next step is due
_U16 = const(65535)
_TICK_HZ = const(1000000)
# arming and cancelling the guard timer on a predicted real Pico: 40 + 17 us warm, ~400 us the
# first time (cold); not counted in the hook's budget, kept free before the next step with it
_GUARD_US = const(100)

# the Admit whose user hook runs under its guard timer now, else None (a callback still queued
# after the timer's deinit then does nothing).  The timer's callback is this module's _take, a
# plain function: a bound method re-arming its own timer raised MemoryError on the board with the
# heap locked
_GUARD = [None]


def _take(t):
    a = _GUARD[0]
    if a is not None:
        a.take(t)


class Admit:
    def __init__(self, app):
        self.app = app
        # the rule reads the app's clock and its step start (App: _ticks, _tdiff, timing.last_us,
        # link_budget_us, period_us); on: the rule applies (host tests may switch it off)
        self._ticks = app._ticks
        self._diff = app._tdiff
        self.on = True
        self.over = 0  # us the last tick with link work ran past its period (the next catches up)
        self.held = 0  # ticks in a row a backlog got no frame (the rule held it)
        self.t0 = 0
        self.lim = 0
        self.plim = 0
        self.force = False
        # planned cost (us) of a decoded frame by message id, and of a REQUEST by requested id
        self.ctab = array("H", [FRAME_US] * 32)
        self.ctab[T.HOST_HEARTBEAT] = HB_US
        self.rtab = array("H", [FRAME_US] * 32)
        for w in (T.STATS_DECODE, T.STATS_FRAMES, T.STATS_LOOP, T.TIMING):
            self.rtab[w] = HEAVY_US
        # the user hook: called in a tick's spare time, within its budget
        self.fn = None
        self.budget = 0
        self.runs = 0
        self.n_over = 0
        # its guard (HAL guard_timer: None, none on this HAL): armed for the next step's
        # deadline while the hook runs, its callback runs that step on time (take)
        self.guard = None
        self._one_shot = 0
        self.dl = 0  # the deadline the guard is armed for
        self.taken = 0  # steps the guard ran during the last call
        self.n_taken = 0  # ... since the start (u16)

    def open(self):
        # (the step's start read now: a TIMING request's reply restarts the app's statistics)
        app = self.app
        self.t0 = app.timing.last_us
        lim = app.link_budget_us - self.over
        self.lim = lim
        self.plim = lim - (app.link_budget_us - app.period_us)
        self.force = self.held >= FORCE

    def fits_now(self, c, k, fresh):
        # the rule at the clock's time now, for a frame of planned cost c (k: frames handled so
        # far in this tick); fresh: read in this tick (limit plim), else held from the last (lim).
        # The CAN link calls it (its planned costs were measured with the call); the serial link
        # writes the same comparison inline
        n = self._diff(self._ticks(), self.t0)
        return n <= (self.plim if fresh else self.lim) - c or (self.force and k == 0)

    def close(self, now, k, backlog):
        if now < 0:
            now = self._diff(self._ticks(), self.t0)
        o = now + self.over - self.app.period_us
        self.over = o if o > 0 else 0
        if backlog:
            self.held = 0 if k else self.held + 1
        else:
            self.held = 0

    def set_user(self, fn, budget_us):
        self.fn = fn
        self.budget = budget_us if budget_us > 0 else 0
        if fn is not None and self.guard is None:
            gt = self.app.hal.guard_timer
            if gt is not None:
                g = gt()
                if g is not None:
                    self._one_shot = g.ONE_SHOT
                    self.guard = g
        return self.on

    def take(self, t):
        # the guard timer's callback (in the main thread, inside the user hook): the tick whose
        # deadline has come, on time (App.guard_tick); armed again for the next deadline
        app = self.app
        app.guard_tick(self.dl)
        self.taken += 1
        if self.n_taken < _U16:
            self.n_taken += 1
        dl = app._tadd(self.dl, app.period_us)
        self.dl = dl
        left = self._diff(dl, self._ticks())
        t.init(mode=self._one_shot, period=left if left > 0 else 1, tick_hz=_TICK_HZ, callback=_take)

    def user(self):
        # fn() is called when its budget still ends _USER_MARGIN us before the next step is due;
        # a call over its budget switches the hook off (n_over counts it) and, when it ran past
        # the period, hands the excess on to the next tick's limit.  With a guard timer (HalPico)
        # a call still running at the next step's deadline is interrupted at its next bytecode
        # by that step (take), once per period it runs on.  Returns the steps the guard ran (App.run
        # goes on from the last of them, App.guard_tick)
        u = self.fn
        if u is None or not self.on:
            return 0
        app = self.app
        diff = self._diff
        t0 = app.timing.last_us
        now = diff(self._ticks(), t0) + self.over
        g = self.guard
        if now + self.budget + (_GUARD_US if g is not None else 0) > app.period_us - _USER_MARGIN:
            return 0
        self.taken = 0
        if g is not None:
            dl = app._tadd(t0, app.period_us)
            self.dl = dl
            left = diff(dl, self._ticks())
            _GUARD[0] = self
            g.init(mode=self._one_shot, period=left if left > 0 else 1, tick_hz=_TICK_HZ, callback=_take)
        s = self._ticks()
        try:
            u()
        finally:
            d = diff(self._ticks(), s)
            if g is not None:
                _GUARD[0] = None
                g.deinit()
        if self.runs < _U16:
            self.runs += 1
        e = diff(self._ticks(), t0) + self.over
        if d > self.budget:
            self.fn = None
            if self.n_over < _U16:
                self.n_over += 1
            if e > app.period_us and not self.taken:
                self.over = e - app.period_us
        if self.taken:
            self.over = 0
        return self.taken
