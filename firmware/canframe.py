# CAN framing (ODrive CAN Simple style): 11-bit id = node_id << 5 | msg_id, classic
# 8-byte payloads, little-endian, the same payload bytes as the serial framing (no
# seq, no extra CRC).  Every message fits one frame (msgtable splits long data).
#
# For virtual buses the frames also travel as python-can's `serial` interface bytes:
#   0xAA, timestamp u32 LE (ms), dlc u8, arbitration id u32 LE, data[dlc], 0xBB
# SerialCanWriter builds those into a preallocated buffer; SerialCanDecoder parses
# them byte by byte without allocating or raising.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

_MSG_BITS = const(5)
_MSG_MASK = const(0x1F)
_NODE_MASK = const(0x3F)
_SOF = const(0xAA)
_EOF = const(0xBB)
_CMAX = const(0x3FFFFFFF)
_UNKNOWN = const(0xFF)


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
    def __init__(self, layout, node):
        self.layout = layout
        self.node = node
        self.data = bytearray(8)
        self.out = bytearray(19)

    def encode(self, mid, vals, voff, ts_ms):
        n = self.layout.pack(mid, vals, voff, self.data, 0)
        return self.frame(mid, n, ts_ms)

    def frame(self, mid, n, ts_ms):
        # wrap data[:n] as message mid; returns the byte count in self.out
        out = self.out
        out[0] = _SOF
        out[1] = ts_ms & 0xFF
        out[2] = (ts_ms >> 8) & 0xFF
        out[3] = (ts_ms >> 16) & 0xFF
        out[4] = (ts_ms >> 24) & 0xFF
        out[5] = n
        cid = can_id(self.node, mid)
        out[6] = cid & 0xFF
        out[7] = cid >> 8
        out[8] = 0
        out[9] = 0
        for i in range(n):
            out[10 + i] = self.data[i]
        out[10 + n] = _EOF
        return 11 + n


class SerialCanDecoder:
    # feed(b) -> message id of a complete frame addressed to `node` with the right
    # length, else -1; payload in self.data[:self.plen].  Drops: n_length (dlc > 8 or
    # wrong for the id), n_framing (missing 0xBB, extended/RTR/error id),
    # n_unknown (unknown msg id), n_other (another node's frame, not an error).
    def __init__(self, layout, node):
        self.plen_of = layout.plen
        self.node = node
        self.data = bytearray(8)
        self.n_ok = 0
        self.n_length = 0
        self.n_framing = 0
        self.n_unknown = 0
        self.n_other = 0
        self.mid = -1
        self.plen = 0
        self._state = 0
        self._i = 0
        self._dlc = 0
        self._id = 0
        self._flags = 0

    def feed(self, b):
        st = self._state
        if st == 0:
            if b == _SOF:
                self._state = 1
                self._i = 0
            return -1
        if st == 1:
            # timestamp, ignored
            self._i += 1
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
            return -1
        if st == 3:
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


class SerialCanTx:
    # sender for commands.Dispatcher over python-can serial-interface bytes
    def __init__(self, writer, write, ticks_ms):
        self.w = writer
        self.write = write
        self.ticks_ms = ticks_ms

    def send(self, mid, seq, vals, voff):
        n = self.w.encode(mid, vals, voff, self.ticks_ms() & 0x3FFFFFFF)
        self.write(self.w.out, n)
