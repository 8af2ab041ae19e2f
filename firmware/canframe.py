# CAN framing (ODrive CAN Simple style): 11-bit id = node_id << 5 | msg_id, classic
# 8-byte payloads, little-endian, the same payload bytes as the serial framing (no
# seq).  Every message fits one frame (msgtable splits long data).
#
# On a byte stream (a UART, a pty) the frames travel as python-can's `serial` interface
# bytes, with a CRC of their own in the timestamp field (a CAN bus has its CRC; a
# stream has none, and one flipped bit must not turn a command into another):
#   0xAA, crc16 u16 LE, 0x00 0x00, dlc u8, arbitration id u32 LE, data[dlc], 0xBB
# crc16 is CRC-16/CCITT-FALSE (crc16.py) over dlc, the 4 id bytes and the data; python-can
# reads the frame unchanged (its timestamp is then crc16 / 1000 s).  SerialCanWriter
# builds those into a preallocated buffer; SerialCanDecoder parses them byte by byte
# without allocating or raising and drops a frame whose CRC does not check out.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from . import crc16

_MSG_BITS = const(5)
_MSG_MASK = const(0x1F)
_NODE_MASK = const(0x3F)
_SOF = const(0xAA)
_EOF = const(0xBB)
_CMAX = const(0x3FFFFFFF)
_UNKNOWN = const(0xFF)
_INIT = const(0xFFFF)


def can_id(node, mid):
    # 11-bit arbitration id
    return ((node & _NODE_MASK) << _MSG_BITS) | (mid & _MSG_MASK)


def node_of(cid):
    return (cid >> _MSG_BITS) & _NODE_MASK


def msg_of(cid):
    return cid & _MSG_MASK


class SerialCanWriter:
    # data: payload scratch (pack into it with Layout.pack(mid, vals, voff, w.data, 0));
    # out: the python-can serial frame
    def __init__(self, layout, node, table=None):
        self.layout = layout
        self.node = node
        self.table = table if table is not None else crc16.make_table()
        self.data = bytearray(8)
        self.out = bytearray(19)

    def encode(self, mid, vals, voff, ts_ms=0):
        n = self.layout.pack(mid, vals, voff, self.data, 0)
        return self.frame(mid, n)

    def frame(self, mid, n, ts_ms=0):
        # wrap data[:n] as message mid; returns the byte count in self.out (the
        # timestamp field carries the CRC: ts_ms is ignored)
        out = self.out
        out[0] = _SOF
        out[3] = 0
        out[4] = 0
        out[5] = n
        cid = can_id(self.node, mid)
        out[6] = cid & 0xFF
        out[7] = cid >> 8
        out[8] = 0
        out[9] = 0
        for i in range(n):
            out[10 + i] = self.data[i]
        crc = crc16.compute(self.table, out, 5, 10 + n)
        out[1] = crc & 0xFF
        out[2] = crc >> 8
        out[10 + n] = _EOF
        return 11 + n


class SerialCanDecoder:
    # feed(b) -> message id of a complete frame addressed to `node` with the right
    # length and CRC, else -1; payload in self.data[:self.plen].  Drops: n_crc (CRC
    # mismatch or timestamp high bytes not 0), n_length (dlc > 8 or wrong for the id),
    # n_framing (missing 0xBB, extended/RTR/error id), n_unknown (unknown msg id),
    # n_sync (runs of bytes outside any frame: a lost start marker), n_other (another
    # node's frame, not an error).
    def __init__(self, layout, node, table=None):
        self.plen_of = layout.plen
        self.node = node
        self.table = table if table is not None else crc16.make_table()
        self.data = bytearray(8)
        self.n_ok = 0
        self.n_crc = 0
        self.n_length = 0
        self.n_framing = 0
        self.n_unknown = 0
        self.n_sync = 0
        self.n_other = 0
        self.mid = -1
        self.plen = 0
        self._state = 0
        self._i = 0
        self._dlc = 0
        self._id = 0
        self._flags = 0
        self._rcrc = 0
        self._crc = _INIT
        self._junk = False

    def _c(self, b):
        c = self._crc
        self._crc = ((c << 8) & 0xFFFF) ^ self.table[((c >> 8) ^ b) & 0xFF]

    def feed(self, b):
        st = self._state
        if st == 0:
            if b == _SOF:
                self._state = 1
                self._i = 0
                self._rcrc = 0
                self._junk = False
            elif not self._junk:
                self._junk = True
                self.n_sync += 1 if self.n_sync < _CMAX else 0
            return -1
        if st == 1:
            # timestamp field: the CRC (u16 LE), then two zero bytes
            i = self._i
            if i == 0:
                self._rcrc = b
            elif i == 1:
                self._rcrc |= b << 8
            elif b:
                self._rcrc = -1
            self._i = i + 1
            if self._i == 4:
                self._state = 2
            return -1
        if st == 2:
            if b > 8:
                self.n_length += 1 if self.n_length < _CMAX else 0
                self._state = 0
                return -1
            self._dlc = b
            self._state = 3
            self._i = 0
            self._id = 0
            self._flags = 0
            self._crc = _INIT
            self._c(b)
            return -1
        if st == 3:
            self._c(b)
            i = self._i
            if i == 0:
                self._id = b
            elif i == 1:
                self._id |= b << 8
            else:
                self._flags |= b
            self._i = i + 1
            if self._i == 4:
                self._i = 0
                self._state = 4 if self._dlc else 5
            return -1
        if st == 4:
            self._c(b)
            self.data[self._i] = b
            self._i += 1
            if self._i == self._dlc:
                self._state = 5
            return -1
        # st == 5: end marker
        self._state = 0
        if b != _EOF or self._flags or self._id > 0x7FF:
            self.n_framing += 1 if self.n_framing < _CMAX else 0
            return -1
        if self._crc != self._rcrc:
            self.n_crc += 1 if self.n_crc < _CMAX else 0
            return -1
        if node_of(self._id) != self.node:
            self.n_other += 1 if self.n_other < _CMAX else 0
            return -1
        mid = self._id & _MSG_MASK
        pl = self.plen_of[mid]
        if pl == _UNKNOWN:
            self.n_unknown += 1 if self.n_unknown < _CMAX else 0
            return -1
        if pl != self._dlc:
            self.n_length += 1 if self.n_length < _CMAX else 0
            return -1
        self.mid = mid
        self.plen = pl
        self.n_ok += 1 if self.n_ok < _CMAX else 0
        return mid

    def drops(self):
        return self.n_crc + self.n_length + self.n_unknown + self.n_framing + self.n_sync

    def fill_counts(self, arr, off):
        # STATS_DECODE fields (crc, length, unknown, framing) then frames in at off + 4
        arr[off] = self.n_crc & 0xFFFF
        arr[off + 1] = self.n_length & 0xFFFF
        arr[off + 2] = self.n_unknown & 0xFFFF
        arr[off + 3] = (self.n_framing + self.n_sync) & 0xFFFF
        arr[off + 4] = self.n_ok


class SerialCanTx:
    # sender for commands.Dispatcher over python-can serial-interface bytes
    def __init__(self, writer, write, ticks_ms=None):
        self.w = writer
        self.write = write
        self.n_sent = 0

    def send(self, mid, seq, vals, voff):
        n = self.w.encode(mid, vals, voff)
        self.write(self.w.out, n)
        self.n_sent = self.n_sent + 1 if self.n_sent < _CMAX else 0
