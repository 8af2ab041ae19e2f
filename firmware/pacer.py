# Periodic messages of a host link, in one place for every main (the board's UART link,
# firmware/link_serial.py, and the HIL main, firmware/main_hil.py): TELEM_STATE +
# TELEM_CTRL every telem_div control ticks and a HEARTBEAT every heartbeat_ms.  Both
# are counted in the board's own time -- control ticks of period_us at the loop rate,
# the clock of uptime_ms -- not in the wall clock of whatever runs the loop.  One
# sequence counter numbers telemetry and heartbeats (the host counts lost periodic
# frames by it).  The first ticks send both, so a host sees a (re)started board at
# once.  A heartbeat due on a tick that sends telemetry goes on the next tick instead
# (when telem_div > 1): no tick carries both, which bounds the longest tick on a board.
# Allocation-free.
#
#   pacer = Pacer(app, disp, params)
#                              app: param_get(index), period_us; disp: commands.Dispatcher;
#                              params (optional): the app's int32 parameter array (T.N_PARAMS
#                              entries, App.params), indexed in tick() without a call; None
#                              (a stand-in app with no array): tick() calls app.param_get
#   pacer.tick()               after every control step
#   pacer.telemetry / .heartbeat  the senders (seq) -> disp.send_telemetry/send_heartbeat;
#                              a link may put faster ones of the same bytes there
#   pacer.elapse(us)           board time passing without control ticks (a HIL
#                              lockstep link waiting for the host): heartbeats only

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from . import msgtable as T

# above any heartbeat_ms (msgtable: at most 10000 ms): the first elapse() sends
_HB_DUE_US = const(10000000)


class Pacer:
    def __init__(self, app, disp, params=None):
        self.app = app
        self.disp = disp
        self.seq = 0
        self._telem_left = 0
        self._hb_us = _HB_DUE_US
        self.telemetry = disp.send_telemetry
        self.heartbeat = disp.send_heartbeat
        # the app's parameter array, indexed in tick() (no method call per tick); None: param_get
        self._p = params

    def tick(self):
        # every control tick; the same as elapse(app.period_us) after the telemetry, in one
        # call (a call costs more than this body on a board).  Its viper build (fasttick.PacerV)
        # is generated from this body (host/boards/fwgen)
        app = self.app
        p = self._p
        if p is not None:
            div = p[T.P_TELEM_DIV]
            hb = p[T.P_HEARTBEAT_MS]
        else:
            div = app.param_get(T.P_TELEM_DIV)
            hb = app.param_get(T.P_HEARTBEAT_MS)
        sent = False
        if div > 0:
            n = self._telem_left - 1
            if n <= 0:
                n = div
                q = (self.seq + 1) & 0xFF
                self.seq = q
                self.telemetry(q)
                sent = div > 1
            self._telem_left = n
        if hb <= 0:
            return
        t = self._hb_us + app.period_us
        if t < hb * 1000 or sent:
            # (due but telemetry went this tick: next tick; t then exceeds by a period at most)
            self._hb_us = t
            return
        self._hb_us = 0
        q = (self.seq + 1) & 0xFF
        self.seq = q
        self.heartbeat(q)

    def elapse(self, us):
        # us: 0 .. 2**20 per call (a period or an idle wait); the sum stays below 2**25
        hb = self.app.param_get(T.P_HEARTBEAT_MS)
        if hb <= 0:
            return
        t = self._hb_us + us
        if t < hb * 1000:
            self._hb_us = t
            return
        self._hb_us = 0
        self.seq = (self.seq + 1) & 0xFF
        self.heartbeat(self.seq)
