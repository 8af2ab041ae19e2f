# The host links' admission rule in predicted time (issue 26), one copy for both links
# (link_serial.SerialLink, link_can.CanLink): a received frame is handled in this tick only when
# its planned cost still ends within the tick's limit, counted from the step's *scheduled* start
# (App: timing.last_us); what does not fit is held for the next tick.  A tick that runs past its
# period hands the excess on (over): the next tick's limit is that much shorter, so it catches
# up.  A backlog held _FORCE ticks in a row gets one frame whatever the time (a loop rate at which
# no frame ever fits still answers, one late tick per _FORCE ticks of traffic).  Then the user
# hook (set_user): called in the spare time that is left, timed, switched off when over budget.
#
#   a = Admit(app)           the limit: app.link_budget_us (11/8 of the period, App) from the
#                            step's scheduled start; it follows the loop rate
#   a.on                     False: the app has no clock/step start (host tests): no time rule
#   a.open()                 start of the tick's receive phase (limit and forcing fixed)
#   a.now()                  us since the step's scheduled start (>= 0; after open())
#   a.fits(now, cost, k)     may a frame of planned cost start now? (k: frames handled so far)
#   a.fits_now(cost, k, fresh)  the same at the clock's time now; fresh: within the period
#   a.close(now, k, backlog) end of the receive phase (now < 0: read the clock); backlog: frames
#                            still waiting (held or unread)
#   a.idle()                 a tick with no receive phase (nothing came in): nothing carried
#   a.user()                 the user hook, if set and its budget fits (after close/idle)
#
# The planned costs (cost()) are measured on the predicted real Pico (the harness's XIP cache
# model, a cold cache: command code runs rarely) -- docs/firmware.md, "Board timing".
# Allocation-free; integers only.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from . import msgtable as T

# a frame's work on a predicted real Pico (us, XIP model, cold cache, measured with the telemetry
# pair every tick on the serial link): a host heartbeat 320; a stats request (three replies)
# 1530, a timing request 1283; every other frame at most ~1090 (arm 1090, excite 1080, param_set
# 1067, gains_chunk 1059, set_reference 979)
HB_US = const(400)
FRAME_US = const(1200)
HEAVY_US = const(1600)
_FORCE = const(8)  # ticks a backlog waits at most before one frame goes whatever the time
_USER_MARGIN = const(100)  # us a user hook leaves before the next step is due
_U16 = const(65535)


def cost(mid, w):
    # planned cost (us) of handling a decoded frame mid (w: its first payload byte)
    if mid == T.HOST_HEARTBEAT:
        return HB_US
    if mid == T.REQUEST and (w == T.STATS_DECODE or w == T.STATS_FRAMES or w == T.STATS_LOOP or w == T.TIMING):
        return HEAVY_US
    return FRAME_US


class Admit:
    def __init__(self, app):
        self.app = app
        self._ticks = app._ticks if hasattr(app, "_ticks") else None
        self._diff = getattr(app, "_tdiff", None)
        # the rule needs the app's clock and its step start (App: timing.last_us)
        self.on = self._ticks is not None and hasattr(app, "link_budget_us") and hasattr(app, "timing")
        self.over = 0  # us the last tick with link work ran past its period (the next catches up)
        self.held = 0  # ticks in a row a backlog got no frame (the rule held it)
        self.t0 = 0
        self.lim = 0
        self.force = False
        # the user hook: called in a tick's spare time, within its budget
        self.fn = None
        self.budget = 0
        self.runs = 0
        self.n_over = 0

    def open(self):
        # (the step's start read now: a TIMING request's reply restarts the app's statistics)
        self.t0 = self.app.timing.last_us
        self.lim = self.app.link_budget_us - self.over
        self.force = self.held >= _FORCE

    def now(self):
        n = self._diff(self._ticks(), self.t0)
        return n if n > 0 else 0

    def fits(self, now, c, k):
        return now <= self.lim - c or (self.force and k == 0)

    def fits_now(self, c, k, fresh):
        # fits() at the clock's time now (one call where the caller keeps no time of its own);
        # fresh: a frame not yet held must end within the period (the excess counted) -- only a
        # frame that has waited a tick may take the 11/8 (CAN: a held frame waits in the driver
        # and costs nothing; the tick after a telemetry tick has the room)
        n = self._diff(self._ticks(), self.t0)
        lim = self.lim
        if fresh:
            lim -= self.app.link_budget_us - self.app.period_us
        return n <= lim - c or (self.force and k == 0)

    def close(self, now, k, backlog):
        if now < 0:
            now = self.now()
        o = now + self.over - self.app.period_us
        self.over = o if o > 0 else 0
        if backlog:
            self.held = 0 if k else self.held + 1
        else:
            self.held = 0

    def idle(self):
        self.over = 0

    def set_user(self, fn, budget_us):
        self.fn = fn
        self.budget = budget_us if budget_us > 0 else 0
        return self.on

    def user(self):
        # fn() is called when its budget still ends _USER_MARGIN us before the next step is due;
        # a call over its budget switches the hook off (n_over counts it) and, when it ran past
        # the period, hands the excess on to the next tick's limit
        u = self.fn
        if u is None or not self.on:
            return
        app = self.app
        diff = self._diff
        t0 = app.timing.last_us
        now = diff(self._ticks(), t0) + self.over
        if now + self.budget > app.period_us - _USER_MARGIN:
            return
        u()
        if self.runs < _U16:
            self.runs += 1
        e = diff(self._ticks(), t0) + self.over
        if e - now > self.budget:
            self.fn = None
            if self.n_over < _U16:
                self.n_over += 1
            if e > app.period_us:
                self.over = e - app.period_us
