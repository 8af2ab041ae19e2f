# Host link of a board in normal (not HIL) operation: COBS serial frames on a UART
# (framing.py), commands dispatched to the app (commands.py), telemetry and heartbeats
# paced by pacer.Pacer (as in the HIL main).  poll() is called by App.run() once per
# tick after the control step; it allocates nothing.  Only HOST_HEARTBEAT and
# SET_REFERENCE frames feed the app's link watchdog (commands.py): a monitor polling the
# board does not keep a dead controlling host alive.
#
# app: the App (firmware/app.py), read as plain attributes -- its emitter (framing.Encoder, the
# pacer, the commands' CRC), its clock _ticks/_tdiff and step start (admit.py) -- no probes.
# uart: machine.UART-like with any() (bytes waiting; a port may say 1 when there are
# more) and readinto(buf, n).  Only bytes any() reported are read: rp2's readinto waits
# for all n bytes (up to an inter-character timeout of >= 1 ms at 1 Mbaud), a stall of
# half a loop period.  write(buf) takes a whole buffer, so one memoryview per frame length
# is made here, once.
#
# Bounded work per tick, in the time a real Pico takes (the emulated board's XIP flash-cache model:
# command code runs rarely, so from a cold cache -- a frame costs 300-1530 us on a predicted real
# Pico, where the same code takes 60-400 us on ideal cycles; docs/firmware.md, "Board timing"):
# poll() sends the periodic frames first (the pacer: on a telem_div 1 tick the telemetry pair,
# ~210 us), then decodes and dispatches frames under the links' admission rule (admit.py, shared
# with link_can.py): a frame is read only when a heartbeat could still follow, and dispatched only
# when the decoding (_SCAN_US) and its kind's cost (admit.py's tables: measured) still end within
# the period (a frame decoded in this tick) or app.link_budget_us (1.5 periods less the larger of
# 1/8 period and admit.REFILL_US: a frame held from the last tick) of the step's scheduled start (a decoded frame that does not fit is
# held for the next tick); a tick that ran past its period hands its excess on.  So no
# frame makes a gap between two step starts longer than 1.5 periods (a late tick, App._period) on
# a predicted real board; at most FRAMES_PER_TICK frames and _RX_TICK bytes per tick, and none
# once this tick's replies reach _SENT frames (the UART's transmit interrupts cost the loop too).
# A backlog held back 8 ticks in a row gets one frame whatever the time (a loop rate at which no
# frame ever fits -- above ~700 Hz on a predicted real Pico -- still answers, one late tick per 8
# ticks of traffic).  Every command's own work is bounded (commands.py, App).
# What is left waits -- bytes already read in self.rx, the rest in the UART's receive
# buffer (HalPico.uart() makes it large) -- for the next tick.  Frames handled after
# waiting are counted (n_deferred) and the longest wait is kept in ticks (wait_max): the
# host reads both (msgtable STATUS: link_deferred, link_wait_max).

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from . import admit
from . import codec
from . import commands
from . import crc16
from . import emitter
from . import framing
from . import msgtable as T

_RX = const(64)
_RX_TICK = const(96)  # bytes decoded per tick at most
FRAMES_PER_TICK = const(4)  # frames dispatched per tick at most (tests read it)
_SENT = const(3)  # ... and none after the replies of this tick reach this many frames
# reading and decoding a frame on a predicted real Pico: up to ~470 us (a frame's own work:
# admit.py's tables)
_HB_US = const(400)  # admit.HB_US: a heartbeat could still follow
_SCAN_US = const(500)
_U16 = const(65535)
_CMAX = const(0x3FFFFFFF)  # frame counter wrap (framing.SerialTx.n_sent)


class ModeSwitch(Exception):
    # MODE hil/repl was ACKed: raised out of poll() (so out of App.run()) once the ACK is
    # written; main.py hands the link to the mode asked for (SerialLink.mode)
    pass


class SerialLink:
    def __init__(self, uart, app):
        self.uart = uart
        self.app = app
        layout = codec.Layout()
        table = crc16.make_table()
        self.dec = framing.Decoder(layout, table)
        # frames packed/CRC'd/stuffed by the app's emitter (viper on the board: fastframe.py)
        enc = framing.Encoder(layout, table, app.emitter)
        mv = memoryview(enc.out)
        self._views = [mv[:k] for k in range(len(enc.out) + 1)]
        self.tx = framing.SerialTx(enc, self._write)
        self.disp = commands.Dispatcher(app, layout, self.tx, table)
        self.disp.dec = self.dec
        # the commands' integrity check (CRC-32) and the pacer of the app's emitter too
        self.disp.crc30 = emitter.command_crc(app.emitter)
        self.pacer = emitter.pacer(app, self.disp)
        self._tick = self.pacer.tick
        # MODE: the mode asked for (-1: stay in robot mode); the exception made now (the
        # heap is locked when it is raised)
        self.mode = -1
        self._switch = ModeSwitch()
        self.disp.on_mode = self._on_mode
        self.rx = bytearray(_RX)
        self._ri = 0  # rx[_ri:_rn]: bytes read and not yet decoded (they wait for the next tick)
        self._rn = 0
        self.n_deferred = 0
        self.wait = 0  # ticks the current backlog has waited
        self.wait_max = 0
        # the admission rule in predicted time and the user hook (admit.py)
        self.adm = admit.Admit(app)
        self._pend = -1  # a decoded frame the budget held (its id; dec.buf keeps it), or -1
        self._pseq = 0
        self._budget = self.adm.on  # (host tests may switch the time rule off)
        self._ticks = app._ticks
        self._diff = app._tdiff
        self._scan = self.dec.scan
        self._uart_write = uart.write
        self._readinto = uart.readinto
        self._any = uart.any
        # periodic frames in one pass (emitter viper/native: framing.Encoder's fastframe call
        # made here directly): the telemetry pair encoded back to back into one buffer and
        # written with one uart.write, the heartbeat likewise -- the same bytes, counted in
        # SerialTx.n_sent as before.  A call costs ~5-10 us on the board; this saves about
        # ten of them on a telemetry tick
        self._ff = enc._fast  # (None: the bytecode emitter)
        if self._ff is not None:
            tx = self.disp.tx
            enc.encode(T.HEARTBEAT, 0, tx, 0)  # the encoder checks tx once (its length)
            self._lut = enc._lut
            self._raw = enc.raw
            w = len(enc.out)
            self._buf2 = bytearray(2 * w)
            mv = memoryview(self._buf2)
            self._at = [mv[k:] for k in range(w + 1)]
            self._upto = [mv[:k] for k in range(2 * w + 1)]
            self.pacer.telemetry = self._telemetry
            self.pacer.heartbeat = self._heartbeat

    def _write(self, buf, n):
        self._uart_write(self._views[n])

    def _telemetry(self, seq):
        # TELEM_STATE + TELEM_CTRL (Dispatcher.send_telemetry's frames) in one write
        tx = self.disp.tx
        self.app.fill_telemetry(tx)
        f = self._ff
        n = f(self._lut, self._raw, self._buf2, tx, 0, T.TELEM_STATE, seq)
        if n > 0:
            m = f(self._lut, self._raw, self._at[n], tx, 4, T.TELEM_CTRL, seq)
            if m > 0:
                self._uart_write(self._upto[n + m])
                # two frames sent (SerialTx.send's count and wrap; never computes 2**30)
                st = self.tx
                n = st.n_sent
                n = n + 1 if n < _CMAX else 0
                st.n_sent = n + 1 if n < _CMAX else 0
                return
        self.disp.send_telemetry(seq)  # not encodable here: the dispatcher's path

    def _heartbeat(self, seq):
        tx = self.disp.tx
        self.app.fill_heartbeat(tx)
        n = self._ff(self._lut, self._raw, self._buf2, tx, 0, T.HEARTBEAT, seq)
        if n > 0:
            self._uart_write(self._upto[n])
            st = self.tx
            st.n_sent = st.n_sent + 1 if st.n_sent < _CMAX else 0
            return
        self.disp.send_heartbeat(seq)

    def poll(self):
        # the periodic frames first (their time counts in the frames' budget), then what came in;
        # idle (nothing received, nothing waiting): the pacer and one any()
        self._tick()
        if self._pend >= 0 or self._ri < self._rn or self._any():
            self._receive()
            if self.mode >= 0:
                raise self._switch
        else:
            self.adm.over = 0
        if self.adm.fn is not None:
            return self.adm.user()
        return 0

    def set_user(self, fn, budget_us):
        # a user hook (docs/firmware.md, "User code in the spare time"; admit.Admit.user): fn()
        # -- no arguments, allocation-free (the heap is locked in the loop), a bound method made
        # once -- is called at most once a tick, after the link's work, only when budget_us still
        # ends 100 us before the next step is due.  Each call is timed: one that takes longer
        # than budget_us switches the hook off (user_over counts it; set_user again to resume).
        # None: no hook.  Returns whether the board's clock times it (False: never called)
        return self.adm.set_user(fn, budget_us)

    @property
    def user_runs(self):
        return self.adm.runs

    @property
    def user_over(self):
        return self.adm.n_over

    def _on_mode(self, m):
        # MODE (commands.py: motor off, m valid): robot is this mode already
        if m != T.MODE_ROBOT:
            self.mode = m
        return T.OK

    def _receive(self):
        # decode and dispatch within this tick's budget (see the top of the file)
        rx = self.rx
        dec = self.dec
        scan = self._scan
        adm = self.adm
        budget = self._budget
        if budget:
            # a frame starts only if it ends within link_budget_us of the step's scheduled start
            # (the previous tick's excess counted), at its kind's cost; a long hold forces one
            # (admit.py: the rule's state and tables there, Admit.open/close's statements inline
            # here -- no call in this path)
            app = self.app
            ticks = self._ticks
            diff = self._diff
            t0 = app.timing.last_us
            lim = app.link_budget_us - adm.over
            plim = lim - (app.link_budget_us - app.period_us)  # a frame decoded in this tick
            force = adm.held >= admit.FORCE
            ctab = adm.ctab
        waited = self.wait > 0
        st = self.tx
        s0 = st.n_sent
        left = _RX_TICK
        k = 0
        i = self._ri
        n = self._rn
        mid = self._pend
        fresh = False  # mid was decoded in this tick (not held from the last one)
        seq = self._pseq
        # the clock is read once per frame before reading and decoding it, and again before its
        # dispatch when bytes had to be read for it (the UART's receive path and the decoding,
        # cold, are the unknown part); else the decoding counts as _SCAN_US
        now = -1
        got = False
        while True:
            if budget and now < 0:
                now = diff(ticks(), t0)
                if now < 0:
                    now = 0
            if mid < 0:
                if budget and now > lim - _SCAN_US - _HB_US and not (force and k == 0):
                    break
                if i >= n:
                    if left <= 0:
                        break
                    m = self._any()
                    if not m:
                        break
                    if m > _RX:
                        m = _RX
                    if m > left:
                        m = left
                    n = self._readinto(rx, m)
                    i = 0
                    got = True
                    if not n:
                        n = 0
                        break
                    left -= n
                mid = scan(rx, i, n)
                i = dec.next
                if mid < 0:
                    continue
                seq = dec.seq
                fresh = True
            # a decoded frame: dispatched if it still fits at its kind's cost -- within the period
            # when decoded in this tick, within app.link_budget_us when held from the last one -- else
            # held (dec.buf keeps it: nothing is scanned before it goes) for the next tick.  So a
            # command whose decoding and cold dispatch do not fit beside the step in one period
            # (a set_reference: ~470 + ~980 us) is decoded in one tick and dispatched at the
            # start of the next
            if budget:
                c = ctab[mid] if mid != T.REQUEST else adm.rtab[dec.buf[2] & 31]
                if got:
                    now = diff(ticks(), t0)
                    got = False
                else:
                    c += _SCAN_US
                if now > (plim if fresh else lim) - c and not (force and k == 0):
                    break
            self.disp.handle(mid, seq, dec.buf, 2)
            mid = -1
            now = -1
            k += 1
            if waited and self.n_deferred < _U16:
                self.n_deferred += 1
            if k >= FRAMES_PER_TICK or ((st.n_sent - s0) & _CMAX) >= _SENT:
                break
        self._pend = mid
        self._pseq = seq
        self._ri = i
        self._rn = n
        backlog = mid >= 0 or i < n or self._any()
        if budget:
            # what this tick ran past its period from its scheduled start: the next one catches up
            # (Admit.close)
            if now < 0:
                now = diff(ticks(), t0)
            o = now + adm.over - app.period_us
            adm.over = o if o > 0 else 0
            if backlog:
                adm.held = 0 if k else adm.held + 1
            else:
                adm.held = 0
        if backlog:
            # a backlog: it waits for the next tick
            w = self.wait + 1
            self.wait = w
            if w > self.wait_max:
                self.wait_max = w if w < _U16 else _U16
        else:
            self.wait = 0
