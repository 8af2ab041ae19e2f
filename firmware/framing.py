# Serial framing: 0x00, COBS([id][seq][payload][crc16 big-endian]), 0x00.
# crc16 is CRC-16/CCITT-FALSE over id, seq, payload; the CRC over the whole unstuffed
# frame (CRC bytes included) is then 0, which is what the decoder checks.
# Encoder writes into a preallocated buffer; Decoder is a byte-at-a-time state
# machine over a preallocated buffer that never raises and never allocates, drops
# bad frames by cause and resynchronises at the next 0x00 (feed(b) per byte, or
# scan(buf, start, end) over a received block).

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from array import array

from . import crc16
from . import msgtable

_MAX_FRAME = const(12)
_MAX_WIRE = const(15)
_UNKNOWN = const(0xFF)
_CMAX = const(0x3FFFFFFF)


class Encoder:
    # raw: unstuffed frame being built (payload at raw[2:]); out: wire bytes.
    # emitter "viper" / "native": encode() packs, CRCs and stuffs a frame in one call of
    # firmware/fastframe.py (same bytes; the module is imported only then: the wasm port
    # has no native emitter) whenever vals is an array (as int32: array('i')); anything
    # else, and "bytecode", takes the plain path below.
    def __init__(self, layout, table=None, emitter="bytecode"):
        self.layout = layout
        self.table = table if table is not None else crc16.make_table()
        self.raw = bytearray(_MAX_FRAME)
        self.out = bytearray(_MAX_WIRE)
        self._fast = None
        self._lut = None
        self._vals = self  # the vals array fastframe may read (self: none yet)
        if emitter != "bytecode":
            from .emitter import frame_encoder
            make_lut, self._fast, self._set_len = frame_encoder(emitter)
            self._lut = make_lut(layout, self.table)

    def encode(self, mid, seq, vals, voff):
        # pack vals[voff:] as message mid, frame it; returns the wire length in self.out
        if vals is self._vals:
            n = self._fast(self._lut, self.raw, self.out, vals, voff, mid, seq)
            if n > 0:
                return n
        elif self._fast is not None and type(vals) is array:
            # a new array (once per array: the dispatcher keeps one): its length bounds
            # what fastframe reads
            self._vals = vals
            self._set_len(self._lut, len(vals))
            return self.encode(mid, seq, vals, voff)
        n = self.layout.pack(mid, vals, voff, self.raw, 2)
        return self.frame(mid, seq, n)

    def frame(self, mid, seq, n):
        # frame raw[2:2+n] (already filled) as message mid with sequence seq
        raw = self.raw
        raw[0] = mid & 0xFF
        raw[1] = seq & 0xFF
        crc = crc16.compute(self.table, raw, 0, 2 + n)
        raw[2 + n] = crc >> 8
        raw[3 + n] = crc & 0xFF
        # COBS stuffing
        out = self.out
        out[0] = 0
        cpos = 1
        code = 1
        o = 2
        for i in range(4 + n):
            b = raw[i]
            if b == 0:
                out[cpos] = code
                cpos = o
                o += 1
                code = 1
            else:
                out[o] = b
                o += 1
                code += 1
                if code == 0xFF:
                    out[cpos] = code
                    cpos = o
                    o += 1
                    code = 1
        out[cpos] = code
        out[o] = 0
        return o + 1


class Decoder:
    # feed(b) -> message id of a complete valid frame, else -1.  After a frame:
    # self.mid, self.seq, self.plen, payload in self.buf[2:2+plen] (valid until the
    # next feed).  Drop counters: n_crc, n_length, n_unknown, n_overrun; n_ok frames.
    def __init__(self, layout, table=None):
        self.plen_of = layout.plen
        self.table = table if table is not None else crc16.make_table()
        self.buf = bytearray(_MAX_FRAME)
        self.n_ok = 0
        self.n_crc = 0
        self.n_length = 0
        self.n_unknown = 0
        self.n_overrun = 0
        self.mid = -1
        self.seq = 0
        self.plen = 0
        self.next = 0
        self.reset()

    def reset(self):
        self._n = 0
        self._left = 0
        self._code = 0
        self._zero = False
        self._skip = False
        self._crc = 0xFFFF

    def _put(self, b):
        n = self._n
        if n >= _MAX_FRAME:
            self._skip = True
            if self.n_overrun < _CMAX:
                self.n_overrun += 1
            return
        self.buf[n] = b
        self._n = n + 1
        c = self._crc
        self._crc = ((c << 8) & 0xFFFF) ^ self.table[((c >> 8) ^ b) & 0xFF]

    def feed(self, b):
        if b == 0:
            return self._end()
        if self._skip:
            return -1
        if self._left == 0:
            # a COBS code byte; the block before it implied a zero (unless code 0xFF)
            if self._zero:
                self._put(0)
                if self._skip:
                    return -1
            self._code = b
            self._left = b - 1
            self._zero = b != 0xFF
        else:
            self._put(b)
            self._left -= 1
        return -1

    def _end(self):
        n = self._n
        skip = self._skip
        empty = n == 0 and self._code == 0
        left = self._left
        crc = self._crc
        self.reset()
        if skip or empty:
            return -1
        if left != 0 or n < 4:
            if self.n_length < _CMAX:
                self.n_length += 1
            return -1
        if crc != 0:
            if self.n_crc < _CMAX:
                self.n_crc += 1
            return -1
        mid = self.buf[0]
        pl = self.plen_of[mid] if mid < 32 else _UNKNOWN
        if pl == _UNKNOWN:
            if self.n_unknown < _CMAX:
                self.n_unknown += 1
            return -1
        if n - 4 != pl:
            if self.n_length < _CMAX:
                self.n_length += 1
            return -1
        self.mid = mid
        self.seq = self.buf[1]
        self.plen = pl
        if self.n_ok < _CMAX:
            self.n_ok += 1
        return mid

    def scan(self, data, start, end):
        # feed data[start:end] until a valid frame completes: returns its id and sets
        # self.next to the index after its delimiter; returns -1 with self.next = end
        # when the bytes run out.  Same results as feed() byte by byte, about twice as
        # fast (the state lives in locals between delimiters).  Usage:
        #   i = 0
        #   while i < n:
        #       mid = dec.scan(rx, i, n)
        #       i = dec.next
        #       if mid >= 0: ...
        n = self._n
        left = self._left
        code = self._code
        zero = self._zero
        skip = self._skip
        crc = self._crc
        buf = self.buf
        tab = self.table
        i = start
        while i < end:
            b = data[i]
            i += 1
            if b == 0:
                self._n = n
                self._left = left
                self._code = code
                self._skip = skip
                self._crc = crc
                m = self._end()
                if m >= 0:
                    self.next = i
                    return m
                n = 0
                left = 0
                code = 0
                zero = False
                skip = False
                crc = 0xFFFF
                continue
            if skip:
                continue
            if left == 0:
                if zero:
                    if n >= _MAX_FRAME:
                        skip = True
                        if self.n_overrun < _CMAX:
                            self.n_overrun += 1
                        continue
                    buf[n] = 0
                    n += 1
                    crc = ((crc << 8) & 0xFFFF) ^ tab[(crc >> 8) & 0xFF]
                code = b
                left = b - 1
                zero = b != 0xFF
            else:
                if n >= _MAX_FRAME:
                    skip = True
                    if self.n_overrun < _CMAX:
                        self.n_overrun += 1
                    continue
                buf[n] = b
                n += 1
                crc = ((crc << 8) & 0xFFFF) ^ tab[((crc >> 8) ^ b) & 0xFF]
                left -= 1
        self._n = n
        self._left = left
        self._code = code
        self._zero = zero
        self._skip = skip
        self._crc = crc
        self.next = end
        return -1

    def drops(self):
        return self.n_crc + self.n_length + self.n_unknown + self.n_overrun

    def fill_counts(self, arr, off):
        # STATS_DECODE fields (crc, length, unknown, framing = overrun) then frames in
        arr[off] = self.n_crc & 0xFFFF
        arr[off + 1] = self.n_length & 0xFFFF
        arr[off + 2] = self.n_unknown & 0xFFFF
        arr[off + 3] = self.n_overrun & 0xFFFF
        arr[off + 4] = self.n_ok


class SerialTx:
    # sender for commands.Dispatcher: encode and write(buf, n) one frame
    def __init__(self, encoder, write):
        self.enc = encoder
        self.write = write
        self.n_sent = 0

    def send(self, mid, seq, vals, voff):
        n = self.enc.encode(mid, seq, vals, voff)
        self.write(self.enc.out, n)
        self.n_sent = self.n_sent + 1 if self.n_sent < _CMAX else 0
