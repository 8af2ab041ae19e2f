# Command dispatcher: a decoded message -> the firmware target (the app), with range
# checks against msgtable.PARAMS before the target is called, NACK(id, reason, seq)
# for every refusal (a refused command changes nothing), and the gain-table upload
# assembled chunk by chunk into a preallocated buffer, CRC-checked over the whole
# table and handed to target.gains_apply only while the motor is off (disarmed or
# fault).
#
# target methods (each returns msgtable.OK or a reason code unless noted):
#   cmd_arm(), cmd_disarm(), cmd_clear_faults(), cmd_set_reference(x_um),
#   param_get(index) -> value, param_set(index, value), gains_apply(buf, nbytes),
#   fill_heartbeat(arr) (HEARTBEAT fields: state, faults, boot, epoch, gains_crc low
#   byte, uptime_ms low 16 bits),
#   optional (class Target: None until a subclass defines it): feed_watchdog()
#   (HOST_HEARTBEAT: the only command that feeds the link watchdog besides
#   set_reference, whose target method feeds it), fill_version(arr)
#   (arr[3] = gains CRC-16, arr[4] = reset cause), fill_stats(arr) (STATS_LOOP fields),
#   fill_telemetry(arr) (TELEM_STATE fields then TELEM_CTRL fields: 8 ints),
#   fill_timing(arr) (TIMING fields: 4 ints),
#   fill_sensors_raw(arr) (SENSORS_RAW fields: adc, enc, pos; on REQUEST),
#   status_get(k) (msgtable STATUS value k, read by PARAM_GET(STATUS_BASE + k)),
#   cmd_save(dispatcher, seq) (SAVE_CONFIG: queue a save; the target answers it later
#   with dispatcher.reply(SAVE_CONFIG, seq, reason)); without fill_sensors_raw or cmd_save
#   their request / SAVE_CONFIG is refused with R_NOT_SUPPORTED.
# target.epoch: the arming token (SESSION.token).  ARM is refused (R_STALE_EPOCH) unless it
# carries the token, GAINS_BEGIN likewise, and an upload ends when the token changes.  The
# commands of msgtable.CHECKED are refused (R_BAD_CHECK) unless their trailing check is the
# CRC-32 of their id byte and the payload bytes before it (low 30 bits of a u32 field, low
# 24 of param_set's 3 raw bytes); GAINS_COMMIT carries the CRC-32 of the whole table, built chunk by chunk.
# sender: any object with send(mid, seq, vals, voff) (framing.SerialTx,
# canframe-based senders, or a test double); its n_sent (if it has one) is STATS_FRAMES'
# frames_out.  dec: the link's decoder (framing.Decoder, canframe.SerialCanDecoder), set
# by the link's owner, for STATS_DECODE and frames_in (zeros without one).

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from array import array

from . import crc16
from . import identity
from .crc32 import Crc32
from . import msgtable as T

_FAULT_STATE = const(3)
_DISARMED = const(0)


class Target:
    # The dispatcher's target: the required methods (header) are the subclass's own; each
    # optional capability is None here (the command is refused with R_NOT_SUPPORTED, or its
    # reply left at zeros) until a subclass defines the method.  App is the firmware's target.
    feed_watchdog = None  # feed_watchdog(): HOST_HEARTBEAT feeds the link watchdog
    fill_version = None  # fill_version(arr): VERSION's gains CRC-16 (arr[3]) and reset cause (arr[4])
    fill_stats = None  # fill_stats(arr): STATS_LOOP fields
    fill_sensors_raw = None  # fill_sensors_raw(arr): SENSORS_RAW fields (on REQUEST)
    cmd_save = None  # cmd_save(dispatcher, seq): SAVE_CONFIG, answered later by dispatcher.reply
    cmd_excite = None  # cmd_excite(mode, amp_mn, div) -> OK or a reason: EXCITE
    fill_session = None  # fill_session(arr): SESSION fields
    status_get = None  # status_get(k) -> int: msgtable STATUS value k (PARAM_GET(STATUS_BASE + k))
    gains_apply_crc = None  # gains_apply_crc(buf, nbytes, crc): the table, its CRC checked by the dispatcher


class Dispatcher:
    def __init__(self, target, layout, sender, table=None):
        self.target = target
        self.layout = layout
        self.sender = sender
        self.table = table if table is not None else crc16.make_table()
        n = len(T.PARAMS)
        self.pmin = array("i", [0] * n)
        self.pmax = array("i", [0] * n)
        for p in T.PARAMS:
            self.pmin[p[0]] = p[3]
            self.pmax[p[0]] = p[4]
        self.nparams = n
        self.rx = array("i", [0] * 8)
        self.tx = array("i", [0] * 8)
        self.gbuf = bytearray(T.GAINS_MAX)
        self.g_len = 0
        self.g_crc = 0
        self.g_run = 0
        self.g_got = 0
        self.g_token = -1
        self.c32 = Crc32()  # command checks and the upload's CRC-32 (chunk by chunk)
        self.crc30 = None  # a faster build of the check's CRC (fastlink.crc32_low30), if set
        self.g32 = Crc32()
        self.g_active = False
        self.n_refused = 0
        self.n_handled = 0
        self.dec = None
        # MODE: the link that runs this dispatcher sets on_mode(mode) -> OK or a reason (it
        # switches after the ACK went out); None: the board has no other mode (NOT_SUPPORTED)
        self.on_mode = None
        # the optional capabilities (Target's None defaults: not supported)
        self._feed = target.feed_watchdog
        self._fill_version = target.fill_version
        self._fill_stats = target.fill_stats
        self._fill_raw = target.fill_sensors_raw
        self._save = target.cmd_save
        self._excite = target.cmd_excite
        self._fill_session = target.fill_session
        self._status = target.status_get
        self._apply_crc = target.gains_apply_crc
        self._counted = hasattr(sender, "n_sent")

    # ---- replies ----
    def _ack(self, mid, seq):
        tx = self.tx
        tx[0] = mid
        tx[1] = seq
        self.sender.send(T.ACK, seq, tx, 0)
        return T.OK

    def _nack(self, mid, seq, reason):
        tx = self.tx
        tx[0] = mid
        tx[1] = reason
        tx[2] = seq
        self.n_refused += 1
        self.sender.send(T.NACK, seq, tx, 0)
        return reason

    def _reply(self, mid, seq, reason):
        if reason:
            return self._nack(mid, seq, reason)
        return self._ack(mid, seq)

    def reply(self, mid, seq, reason):
        # a deferred answer (SAVE_CONFIG: the target calls this once the save has run)
        return self._reply(mid, seq, reason)

    def _param_value(self, index, seq):
        tx = self.tx
        tx[0] = index
        tx[1] = self.target.param_get(index)
        self.sender.send(T.PARAM_VALUE, seq, tx, 0)
        return T.OK

    # ---- periodic / requested messages ----
    def send_heartbeat(self, seq):
        self.target.fill_heartbeat(self.tx)
        self.sender.send(T.HEARTBEAT, seq, self.tx, 0)

    def send_telemetry(self, seq):
        self.target.fill_telemetry(self.tx)
        self.sender.send(T.TELEM_STATE, seq, self.tx, 0)
        self.sender.send(T.TELEM_CTRL, seq, self.tx, 4)

    def send_timing(self, seq):
        self.target.fill_timing(self.tx)
        self.sender.send(T.TIMING, seq, self.tx, 0)

    def send_version(self, seq):
        tx = self.tx
        tx[3] = 0
        tx[4] = 0
        if self._fill_version is not None:
            self._fill_version(tx)
        tx[0] = identity.FW_VERSION
        tx[1] = identity.TABLE_HASH
        tx[2] = identity.PARAM_HASH
        self.sender.send(T.VERSION, seq, tx, 0)

    def send_stats(self, seq):
        # STATS_DECODE, STATS_FRAMES, STATS_LOOP
        tx = self.tx
        for i in range(8):
            tx[i] = 0
        if self.dec is not None:
            self.dec.fill_counts(tx, 0)
        self.sender.send(T.STATS_DECODE, seq, tx, 0)
        if self._counted:
            tx[5] = self.sender.n_sent
        self.sender.send(T.STATS_FRAMES, seq, tx, 4)
        for i in range(4):
            tx[i] = 0
        if self._fill_stats is not None:
            self._fill_stats(tx)
        self.sender.send(T.STATS_LOOP, seq, tx, 0)

    def _motor_off(self):
        # disarmed or fault (state from the heartbeat fields): a gain table may be
        # applied (a latched gains fault is fixed by uploading a good table)
        self.target.fill_heartbeat(self.tx)
        st = self.tx[0]
        return st == _DISARMED or st == _FAULT_STATE

    # ---- dispatch ----
    def handle(self, mid, seq, buf, off):
        # message mid (payload at buf[off:], length already checked by the decoder).
        # Returns OK or the reason sent in a NACK; -1 when the message is not a
        # command (HIL_SENSOR: the HIL HAL consumes it).
        if mid == T.HIL_SENSOR:
            return -1
        if mid > T.MAX_ID or self.layout.direction[mid] != T.TO_BOARD:
            return self._nack(mid, seq, T.R_UNKNOWN)
        self.n_handled += 1
        rx = self.rx
        nf = self.layout.unpack(mid, buf, off, rx, 0)
        tg = self.target
        if mid in T.CHECKED and not self._check_ok(mid, buf, off, rx[nf - 1]):
            return self._nack(mid, seq, T.R_BAD_CHECK)
        if mid == T.SET_REFERENCE:
            x = rx[0]
            lim = tg.param_get(T.P_REF_LIMIT)
            if x > lim or x < -lim:
                return self._nack(mid, seq, T.R_OUT_OF_RANGE)
            return self._reply(mid, seq, tg.cmd_set_reference(x))
        if mid == T.HOST_HEARTBEAT:
            if self._feed is not None:
                self._feed()
            return T.OK
        if mid == T.ARM:
            tg.fill_heartbeat(self.tx)
            if self.tx[1] != 0 or self.tx[0] == _FAULT_STATE:
                return self._nack(mid, seq, T.R_FAULTED)
            if rx[0] != tg.epoch:
                return self._nack(mid, seq, T.R_STALE_EPOCH)
            return self._reply(mid, seq, tg.cmd_arm())
        if mid == T.DISARM:
            return self._reply(mid, seq, tg.cmd_disarm())
        if mid == T.CLEAR_FAULTS:
            return self._reply(mid, seq, tg.cmd_clear_faults())
        if mid == T.PARAM_GET:
            i = rx[0]
            if i >= self.nparams:
                k = i - T.STATUS_BASE
                if k < 0 or k >= T.N_STATUS or self._status is None:
                    return self._nack(mid, seq, T.R_BAD_INDEX)
                tx = self.tx
                tx[0] = i
                tx[1] = self._status(k)
                self.sender.send(T.PARAM_VALUE, seq, tx, 0)
                return T.OK
            return self._param_value(i, seq)
        if mid == T.PARAM_SET:
            i = rx[0]
            if i >= self.nparams:
                if T.STATUS_BASE <= i < T.STATUS_BASE + T.N_STATUS:
                    return self._nack(mid, seq, T.R_READ_ONLY)
                return self._nack(mid, seq, T.R_BAD_INDEX)
            v = rx[1]
            if v < self.pmin[i] or v > self.pmax[i]:
                return self._nack(mid, seq, T.R_OUT_OF_RANGE)
            r = tg.param_set(i, v)
            if r:
                return self._nack(mid, seq, r)
            return self._param_value(i, seq)
        if mid == T.GAINS_BEGIN:
            if rx[2] != tg.epoch:
                # not this session's upload (sent before a reset, disarm or fault)
                self.g_active = False
                return self._nack(mid, seq, T.R_STALE_EPOCH)
            return self._gains_begin(rx[0], rx[1], seq)
        if mid == T.GAINS_CHUNK:
            return self._gains_chunk(rx[0], buf, rx[1], seq)
        if mid == T.GAINS_COMMIT:
            return self._gains_commit(seq, rx[0])
        if mid == T.SAVE_CONFIG:
            # queued by the target (cmd_save(dispatcher, seq)); answered through reply() when done
            if self._save is None:
                return self._nack(mid, seq, T.R_NOT_SUPPORTED)
            r = self._save(self, seq)
            if r:
                return self._nack(mid, seq, r)
            return T.OK
        if mid == T.MODE:
            if rx[0] > T.MODE_REPL:
                return self._nack(mid, seq, T.R_OUT_OF_RANGE)
            if not self._motor_off():
                return self._nack(mid, seq, T.R_ARMED)
            if self.on_mode is None:
                return self._nack(mid, seq, T.R_NOT_SUPPORTED)
            return self._reply(mid, seq, self.on_mode(rx[0]))
        if mid == T.EXCITE:
            if self._excite is None:
                return self._nack(mid, seq, T.R_NOT_SUPPORTED)
            return self._reply(mid, seq, self._excite(rx[0], rx[2], rx[1]))
        if mid == T.REQUEST:
            w = rx[0]
            if w == T.HEARTBEAT:
                self.send_heartbeat(seq)
            elif w == T.SESSION:
                tx = self.tx
                tx[0] = tg.epoch
                tx[1] = 0
                if self._fill_session is not None:
                    self._fill_session(tx)
                self.sender.send(T.SESSION, seq, tx, 0)
            elif w == T.TELEM_STATE or w == T.TELEM_CTRL:
                self.send_telemetry(seq)
            elif w == T.TIMING:
                self.send_timing(seq)
            elif w == T.VERSION:
                self.send_version(seq)
            elif w == T.SENSORS_RAW and self._fill_raw is not None:
                self._fill_raw(self.tx)
                self.sender.send(T.SENSORS_RAW, seq, self.tx, 0)
            elif w == T.STATS_DECODE or w == T.STATS_FRAMES or w == T.STATS_LOOP:
                self.send_stats(seq)
            else:
                return self._nack(mid, seq, T.R_NOT_SUPPORTED)
            return T.OK
        return self._nack(mid, seq, T.R_UNKNOWN)

    def _check_ok(self, mid, buf, off, got):
        # the integrity check of a CHECKED command: CRC-32 of the id byte and the payload before
        # the check (crc32.Crc32 written out with locals: a few bytes, ~100 us on a Pico);
        # got: the received u32's 30 bits, or (param_set) the offset of its 3 check bytes
        c = self.c32
        th = c.th
        tl = c.tl
        w = 3 if mid == T.PARAM_SET else 4
        f = self.crc30
        if f is not None:
            # the viper build (link_serial sets it on a board: fastlink.crc32_low30)
            v = f(th, tl, mid, buf, off, self.layout.plen[mid] - w)
            if w == 3:
                return (v & 0xFFFFFF) == (buf[got] | (buf[got + 1] << 8) | (buf[got + 2] << 16))
            return v == got
        k = (0xFFFF ^ mid) & 0xFF
        lo = 0xFFFF ^ tl[k]
        hi = 0xFF ^ th[k]
        i = off
        end = off + self.layout.plen[mid] - w
        while i < end:
            k = (lo ^ buf[i]) & 0xFF
            lo = ((lo >> 8) | ((hi & 0xFF) << 8)) ^ tl[k]
            hi = (hi >> 8) ^ th[k]
            i += 1
        lo ^= 0xFFFF
        hi ^= 0xFFFF
        if w == 3:
            return ((hi & 0xFF) << 16 | lo) == (buf[got] | (buf[got + 1] << 8) | (buf[got + 2] << 16))
        return ((hi & 0x3FFF) << 16 | lo) == got

    # ---- gain table upload ----
    def _gains_begin(self, nbytes, crc, seq):
        if nbytes < 1 or nbytes > T.GAINS_MAX:
            self.g_active = False
            return self._nack(T.GAINS_BEGIN, seq, T.R_BAD_LENGTH)
        self.g_len = nbytes
        self.g_crc = crc
        self.g_got = 0
        self.g_run = crc16.INIT  # CRC of the bytes received so far (one chunk's worth per chunk)
        self.g32.start()
        self.g_token = self.target.epoch
        self.g_active = True
        return self._ack(T.GAINS_BEGIN, seq)

    def _gains_chunk(self, offset, buf, doff, seq):
        if not self.g_active:
            return self._nack(T.GAINS_CHUNK, seq, T.R_BAD_SEQUENCE)
        if self.g_token != self.target.epoch:
            # the session that began the upload ended (disarm, fault): the upload with it
            self.g_active = False
            return self._nack(T.GAINS_CHUNK, seq, T.R_STALE_EPOCH)
        got = self.g_got
        n = self.g_len - offset
        if n > T.CHUNK_BYTES:
            n = T.CHUNK_BYTES
        if offset < got and offset + n == got:
            # the previous chunk again (its ACK was lost): idempotent
            return self._ack(T.GAINS_CHUNK, seq)
        if offset != got or n <= 0:
            self.g_active = False
            return self._nack(T.GAINS_CHUNK, seq, T.R_BAD_SEQUENCE)
        g = self.gbuf
        tb = self.table
        c = self.g_run
        for i in range(n):
            b = buf[doff + i]
            g[offset + i] = b
            c = ((c << 8) & 0xFFFF) ^ tb[((c >> 8) ^ b) & 0xFF]
        self.g_run = c
        self.g32.feed(buf, doff, n)
        self.g_got = got + n
        return self._ack(T.GAINS_CHUNK, seq)

    def _gains_commit(self, seq, check):
        # bounded: the CRCs were built chunk by chunk (_gains_chunk); the state is checked first
        if not self._motor_off():
            # upload kept: disarm and commit again
            return self._nack(T.GAINS_COMMIT, seq, T.R_ARMED)
        if not self.g_active:
            return self._nack(T.GAINS_COMMIT, seq, T.R_BAD_SEQUENCE)
        if self.g_token != self.target.epoch:
            self.g_active = False
            return self._nack(T.GAINS_COMMIT, seq, T.R_STALE_EPOCH)
        if self.g_got != self.g_len:
            return self._nack(T.GAINS_COMMIT, seq, T.R_INCOMPLETE)
        if self.g_run != self.g_crc:
            self.g_active = False
            return self._nack(T.GAINS_COMMIT, seq, T.R_BAD_CRC)
        if self.g32.low30() != check:
            self.g_active = False
            return self._nack(T.GAINS_COMMIT, seq, T.R_BAD_CHECK)
        self.g_active = False
        if self._apply_crc is not None:
            return self._reply(T.GAINS_COMMIT, seq, self._apply_crc(self.gbuf, self.g_len, self.g_crc))
        return self._reply(T.GAINS_COMMIT, seq, self.target.gains_apply(self.gbuf, self.g_len))
