# Host link of a board on a CAN bus: an MCP2515 on SPI (mcp2515.py) carrying the message
# table as CAN frames (11-bit id = node_id << 5 | msg_id, DLC = payload length, no seq: see
# canframe.py), commands dispatched to the app (commands.py), telemetry and heartbeats paced
# by pacer.Pacer -- the same as link_serial.SerialLink, so App.run() and the control loop do
# not change.  poll() is called once per tick after the control step; it allocates nothing.
#
# Receive: the chip's acceptance filters pass only this node's ids; poll() looks at the chip
# only when its INT pin is low (no SPI at all on a quiet tick), then reads CANINTF+EFLG in one
# transaction and the receive buffers (RXB0 rolls over into RXB1).  A frame with an unknown
# or host-bound message id for this node (n_unknown), a DLC that is not the message's length
# (n_length), or an extended/remote frame (n_framing) is dropped and counted; a receive
# buffer overflow (RXnOVR) is counted as framing (STATS_DECODE.framing) and in STATS_CAN.
#
# Bounded work per tick, in the time a real Pico takes (the emulated board's XIP flash-cache
# model): poll() queues the periodic frames first (the pacer), then reads and dispatches frames
# under the links' admission rule (admit.py, shared with link_serial.py): a frame read (its kind
# is known only then) is dispatched only when its kind's cost (admit.py's, plus _CAN_US) and the
# SPI loads queued by then (_LOAD_US each) still end within the period (a frame just read) or
# app.link_budget_us (a frame held a tick: 1.5 periods less admit.REFILL_US or 1/8 period) of the step's scheduled start;
# else it is held (the driver's receive registers keep
# it: nothing else is read before it goes) for the next tick, and what is still in the chip
# stays there (two buffers; a third frame is an overflow, counted).  A tick that ran past its
# period hands the excess on.  The flags are read whenever INT is low, held frame or not: an
# error state change (bus-off: F_CAN) is handled in its tick.  With the viper emitter (App
# config "emitter") payloads are packed by fastcan.py (generated from codec.Layout.pack and
# _fill below by host/boards/fwgen/fastcan.py: `upright generate` after editing either).
#
# Transmit: send() packs the payload straight into a slot of a software queue (two rings: heartbeat, replies
# and stats before telemetry; a full ring drops the new frame, counted in tx_dropped); the end
# of poll() loads free TX buffers in queue order, highest TXB priority first (TXB0 TXP 3 ..
# TXB2 TXP 1), and starts them with one RTS.  Only buffers this link started are asked about
# (READ STATUS), so an idle tick costs no SPI.
#
# Errors: ERRIF (an error state change or a receive overflow) reads TEC/REC and EFLG; every
# change of the error state (EWARN, RXWAR, TXWAR, RXEP, TXEP, TXBO) is reported to the host
# with STATS_CAN (also sent on REQUEST(STATS_CAN)).  Bus-off (TXBO): pending transmissions are
# aborted and the queue emptied (stale commands' replies must not go out later), the
# supervisor latches F_CAN (motor off in the same tick) and latches it again on every tick
# while bus-off, so a clear_faults cannot take effect before the bus has recovered; the
# MCP2515 recovers by itself after 128 x 11 recessive bits, the link sees TXBO clear (ERRIF, or
# EFLG re-read every _BO_POLL ticks while bus-off), reports it, and the host clears the fault.
# A controller that does not answer at start-up (wiring) is F_CAN latched for good: the loop
# runs with the motor off and the USB console says why.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from array import array

from . import admit
from . import codec
from . import commands
from . import crc16
from . import mcp2515 as C
from . import msgtable as T
from .pacer import Pacer
from .supervisor import FAULT, F_CAN

_SLOT = const(14)   # a LOAD TX BUFFER transaction: instruction, SIDH SIDL EID8 EID0 DLC D0..D7
_NHI = const(8)     # slots: heartbeat, replies, stats
_NLO = const(4)     # slots: telemetry
_BO_POLL = const(50)  # ticks between EFLG reads while bus-off
_CMAX = const(0x3FFFFFFF)
_UNKNOWN = const(0xFF)
_RXIF = const(0x03)
_ERRF = const(0xA0)  # ERRIF | MERRF
_STATE_BITS = const(0x3F)  # EFLG error-state bits (not the overflow flags)
# on a predicted real Pico (XIP model): one SPI transaction of the flush (READ STATUS, a LOAD TX
# BUFFER, RTS) 65-130 us; a frame's path through this link beyond the dispatcher's own work
# (admit.cost: measured on the serial link), cold: a host heartbeat's tick costs ~1170 us over an
# idle one here (CANINTF/EFLG and the receive buffer read ~450, the dispatch ~720), 320 on serial
_CAN_US = const(400)
_LOAD_US = const(100)

_ERRORS = ("", "no answer on SPI (controller absent or miswired: check SCK/MOSI/MISO/CS and 3V3)",
           "no bit timing for this bit rate and crystal", "the controller did not enter normal mode")


class CanLink:
    def __init__(self, drv, app, bitrate=500000, xtal_hz=16000000, node=None):
        self.drv = drv
        self.app = app
        layout = codec.Layout()
        self.layout = layout
        self.plen = layout.plen
        self.dirn = layout.direction
        self.node = app.param_get(T.P_NODE_ID) if node is None else node
        self.data = bytearray(8)
        # queue slots: each one whole SPI transaction, filled in place (no copy on the way out)
        self.hi = [bytearray(_SLOT) for _ in range(_NHI)]
        self.lo = [bytearray(_SLOT) for _ in range(_NLO)]
        self.hi_head = 0
        self.hi_n = 0
        self.lo_head = 0
        self.lo_n = 0
        self.busy = 0  # TX buffers this link started and has not seen finish
        self.n_sent = 0
        self.n_ok = 0
        self.n_length = 0
        self.n_unknown = 0
        self.n_framing = 0
        self.n_other = 0
        self.n_overflow = 0
        self.n_busoff = 0
        self.n_tx_drop = 0
        self.eflg = 0
        self.bus_off = False
        self._bo_left = 0
        self.vals = array("i", [0] * 8)
        table = crc16.make_table()
        self.disp = commands.Dispatcher(app, layout, self, table)
        self.disp.dec = self
        self.pacer = Pacer(app, self.disp, app.params)
        self._motor = app.hal.set_motor
        # payloads packed in viper on the board (fastcan.py), else codec.Layout.pack
        self._pk = None
        if app.emitter == "viper":
            from .fastcan import frame_viper
            self._pk = frame_viper
        self._codes = layout.codes
        self._nf = layout.nfields
        # the admission rule in predicted time and the user hook (admit.py)
        self.adm = admit.Admit(app)
        self._budget = self.adm.on
        self._pend = -1  # a frame read and held by the rule (its id; the driver's rdata keeps it)
        self.err = drv.init(bitrate, xtal_hz, self.node)
        self.ok = self.err == C.OK
        if not self.ok:
            print("link_can: MCP2515 start-up failed:", _ERRORS[self.err], "-> fault F_CAN, motor off")
            self._latch()

    # ---- sender for commands.Dispatcher and the Pacer ----
    def send(self, mid, seq, vals, voff):
        q = self._slot(mid)
        if q is not None:
            pk = self._pk
            if pk is not None and voff + self._nf[mid] <= len(vals):
                # id, DLC and payload in one viper call (the same bytes as _fill's)
                pk(self._codes, self._nf, vals, voff, mid, q, ((self.node & 0x3F) << 5) | (mid & 0x1F))
                self.n_sent = self.n_sent + 1 if self.n_sent < _CMAX else 0
            else:
                self._fill(q, mid, self.layout.pack(mid, vals, voff, q, 6))

    def _slot(self, mid):
        # the next free slot of mid's ring (counted as queued), or None: dropped and counted
        if not self.ok or self.bus_off:
            self.n_tx_drop += 1 if self.n_tx_drop < _CMAX else 0
            return None
        if mid == T.TELEM_STATE or mid == T.TELEM_CTRL:
            if self.lo_n >= _NLO:
                self.n_tx_drop += 1 if self.n_tx_drop < _CMAX else 0
                return None
            i = self.lo_head + self.lo_n
            self.lo_n += 1
            return self.lo[i - _NLO if i >= _NLO else i]
        if self.hi_n >= _NHI:
            self.n_tx_drop += 1 if self.n_tx_drop < _CMAX else 0
            return None
        i = self.hi_head + self.hi_n
        self.hi_n += 1
        return self.hi[i - _NHI if i >= _NHI else i]

    def _fill(self, q, mid, n):
        # id and DLC of a slot whose payload is in q[6:6+n]
        cid = ((self.node & 0x3F) << 5) | (mid & 0x1F)
        q[1] = cid >> 3
        q[2] = (cid & 7) << 5
        q[3] = 0
        q[4] = 0
        q[5] = n
        self.n_sent = self.n_sent + 1 if self.n_sent < _CMAX else 0

    # ---- STATS_DECODE fields (commands.Dispatcher.send_stats) ----
    def fill_counts(self, arr, off):
        # crc (the bus's CRC is the controller's: REC counts it), length, unknown, framing
        arr[off] = 0
        arr[off + 1] = self.n_length & 0xFFFF
        arr[off + 2] = self.n_unknown & 0xFFFF
        arr[off + 3] = (self.n_framing + self.n_overflow) & 0xFFFF
        arr[off + 4] = self.n_ok

    def send_stats_can(self):
        v = self.vals
        v[0] = self.drv.tec
        v[1] = self.drv.rec
        v[2] = self.eflg
        v[3] = self.n_busoff & 0xFFFF
        v[4] = self.n_overflow & 0xFFFF
        v[5] = self.n_tx_drop if self.n_tx_drop < 255 else 255
        q = self._slot(T.STATS_CAN)
        if q is not None:
            self._fill(q, T.STATS_CAN, self.layout.pack(T.STATS_CAN, v, 0, q, 6))

    # ---- the tick ----
    def _latch(self):
        sup = self.app.sup
        if not sup.faults & F_CAN:
            self._motor(0)
            self.app.duty = 0
        sup.faults |= F_CAN
        sup.state = FAULT

    def poll(self):
        if not self.ok:
            self._latch()
            return
        # the periodic frames first (queued; their SPI loads count in the frames' plan)
        self.pacer.tick()
        if self._pend >= 0 or self.drv.pending():
            self._service()
        else:
            self.adm.over = 0
        if self.bus_off:
            self._latch()
            self._bo_left -= 1
            if self._bo_left <= 0:
                self._bo_left = _BO_POLL
                self._service()
        if self.hi_n or self.lo_n:
            self._flush()
        if self.adm.fn is not None:
            return self.adm.user()
        return 0

    def set_user(self, fn, budget_us):
        # the user hook, as link_serial.SerialLink.set_user (admit.Admit.user): called after the
        # link's work and the flush, in the spare time
        return self.adm.set_user(fn, budget_us)

    def _service(self):
        # the held frame, then the chip's flags and receive buffers, within this tick's budget
        # (admit.py: Admit.fits_now)
        drv = self.drv
        adm = self.adm
        budget = self._budget
        if budget:
            adm.open()
        k = 0
        mid = self._pend
        held = False
        if mid >= 0:
            if budget:
                # held a tick: it may end within app.link_budget_us
                held = not adm.fits_now(self._plan(mid), 0, False)
            if not held:
                self._pend = -1
                self._dispatch(mid)
                k = 1
        left = 0
        if drv.pending():
            # the flags always (an error state change is handled in this tick, held frame or not)
            drv.flags()
            f = drv.intf
            left = f & _RXIF
            b = 1
            while left and b <= 2 and not held:
                if left & b:
                    # read (its kind is known once it is read: a frame that does not fit then is
                    # held), dispatched when its plan ends within the period
                    left &= ~b
                    mid = self._rx(b - 1)
                    if mid >= 0:
                        if budget and not adm.fits_now(self._plan(mid), k, True):
                            self._pend = mid
                            break
                        self._dispatch(mid)
                        k += 1
                b <<= 1
            if f & _ERRF or self.bus_off:
                self._errors()
        if budget:
            adm.close(-1, k, self._pend >= 0 or left)

    def _plan(self, mid):
        # a read frame's planned cost: its kind's (admit.py), this link's own part, and the SPI
        # loads queued by then and its reply
        adm = self.adm
        c = adm.ctab[mid] if mid != T.REQUEST else adm.rtab[self.drv.rdata[0] & 31]
        return c + _CAN_US + (self.hi_n + self.lo_n + 3) * _LOAD_US

    def _rx(self, k):
        # read RXBk; its message id when it is a frame for this board, else -1 (dropped, counted)
        drv = self.drv
        drv.read_rx(k)
        rid = drv.rid
        if rid < 0:
            self.n_framing += 1 if self.n_framing < _CMAX else 0
            return -1
        if (rid >> 5) != self.node:
            self.n_other += 1 if self.n_other < _CMAX else 0
            return -1
        mid = rid & 0x1F
        pl = self.plen[mid]
        if pl == _UNKNOWN or self.dirn[mid] != T.TO_BOARD:
            self.n_unknown += 1 if self.n_unknown < _CMAX else 0
            return -1
        if pl != drv.rdlc:
            self.n_length += 1 if self.n_length < _CMAX else 0
            return -1
        self.n_ok += 1 if self.n_ok < _CMAX else 0
        return mid

    def _dispatch(self, mid):
        # the frame in the driver's receive registers
        d = self.drv.rdata
        if mid == T.REQUEST and d[0] == T.STATS_CAN:
            self.drv.counters()
            self.send_stats_can()
            return
        self.disp.handle(mid, 0, d, 0)

    def _errors(self):
        drv = self.drv
        e = drv.eflg
        drv.counters()
        if e & (C.RX0OVR | C.RX1OVR):
            self.n_overflow += 1 if self.n_overflow < _CMAX else 0
        drv.clear_errors()
        if e & C.TXBO:
            if not self.bus_off:
                self.bus_off = True
                self._bo_left = _BO_POLL
                self.n_busoff += 1 if self.n_busoff < _CMAX else 0
                drv.abort()
                self.busy = 0
                self.hi_n = 0
                self.lo_n = 0
                self._pend = -1  # a held command goes with them
                self._latch()
        elif self.bus_off:
            self.bus_off = False
        if (e ^ self.eflg) & _STATE_BITS:
            self.eflg = e & _STATE_BITS
            self.send_stats_can()

    def _flush(self):
        drv = self.drv
        if self.busy:
            self.busy &= drv.tx_busy()
        free = 7 & ~self.busy
        if not free:
            return
        start = 0
        for k in range(3):
            b = 1 << k
            if not free & b:
                continue
            if self.hi_n:
                drv.load_frame(k, self.hi[self.hi_head])
                self.hi_head = self.hi_head + 1 if self.hi_head + 1 < _NHI else 0
                self.hi_n -= 1
            elif self.lo_n:
                drv.load_frame(k, self.lo[self.lo_head])
                self.lo_head = self.lo_head + 1 if self.lo_head + 1 < _NLO else 0
                self.lo_n -= 1
            else:
                break
            start |= b
        if start:
            drv.rts(start)
            self.busy |= start
