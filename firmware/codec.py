# Payload codec driven by msgtable: little-endian fields <-> preallocated int arrays.
# Layout() is built once at start-up (it walks the table); pack/unpack then
# allocate nothing and never raise for a known id with an in-range buffer.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from . import msgtable

_NIDS = const(32)
_MAXF = const(8)
_SIGNED = const(0x80)
_RAW = const(0x40)
_SIZE = const(0x3F)
UNKNOWN = const(0xFF)
_SMALL = const(0x3FFFFFFF)


def _code(fmt):
    # struct code -> size | flags
    if fmt[-1] == "s":
        return _RAW | int(fmt[:-1])
    size = {"B": 1, "b": 1, "H": 2, "h": 2, "I": 4, "i": 4}[fmt]
    return size | (_SIGNED if fmt in "bhi" else 0)


class Layout:
    # per-id payload length (UNKNOWN if no such message), direction, field codes
    def __init__(self):
        self.plen = bytearray(b"\xff" * _NIDS)
        self.nfields = bytearray(_NIDS)
        self.direction = bytearray(_NIDS)
        self.codes = bytearray(_NIDS * _MAXF)
        for m in msgtable.MESSAGES:
            mid = m[0]
            n = 0
            k = 0
            for f in m[4]:
                c = _code(f[1])
                self.codes[mid * _MAXF + k] = c
                n += c & _SIZE
                k += 1
            self.plen[mid] = n
            self.nfields[mid] = k
            self.direction[mid] = m[2]

    def pack(self, mid, vals, voff, buf, off):
        # write fields vals[voff:] of message mid into buf[off:]; returns payload length.
        # Raw-byte fields are left untouched in buf (the caller fills them).
        base = mid * _MAXF
        codes = self.codes
        for k in range(self.nfields[mid]):
            c = codes[base + k]
            size = c & _SIZE
            if not c & _RAW:
                v = vals[voff + k]
                buf[off] = v & 0xFF
                if size > 1:
                    buf[off + 1] = (v >> 8) & 0xFF
                    if size > 2:
                        buf[off + 2] = (v >> 16) & 0xFF
                        buf[off + 3] = (v >> 24) & 0xFF
            off += size
        return self.plen[mid]

    def unpack(self, mid, buf, off, vals, voff):
        # read the fields of message mid from buf[off:] into vals[voff:]; returns the
        # field count.  u32 keeps its low 30 bits, i32 saturates to +-(2**30-1) so every
        # value is a small int; a raw-byte field yields its byte offset in buf.
        base = mid * _MAXF
        codes = self.codes
        n = self.nfields[mid]
        for k in range(n):
            c = codes[base + k]
            size = c & _SIZE
            if c & _RAW:
                v = off
            elif size == 1:
                v = buf[off]
                if c & _SIGNED and v > 127:
                    v -= 256
            elif size == 2:
                v = buf[off] | (buf[off + 1] << 8)
                if c & _SIGNED and v > 32767:
                    v -= 65536
            else:
                top = buf[off + 3]
                if c & _SIGNED:
                    if top > 127:
                        top -= 256
                    if top > 63:
                        v = _SMALL
                    elif top < -64:
                        v = -_SMALL
                    else:
                        v = (top << 24) | (buf[off + 2] << 16) | (buf[off + 1] << 8) | buf[off]
                        if v < -_SMALL:
                            v = -_SMALL
                else:
                    v = ((top & 0x3F) << 24) | (buf[off + 2] << 16) | (buf[off + 1] << 8) | buf[off]
            vals[voff + k] = v
            off += size
        return n
