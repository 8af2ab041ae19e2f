# CRC-32/ISO-HDLC (zlib.crc32: reflected poly 0xEDB88320, init and xorout 0xFFFFFFFF) in
# small ints: the 32-bit register is two 16-bit halves (hi, lo) and the table two arrays of
# 16-bit halves, so nothing leaves -2**30..2**30-1 on a 32-bit port and nothing allocates
# after make().  The integrity check of the commands that move the cart (msgtable CHECKED)
# and the gain upload's second CRC (GAINS_COMMIT.check).
#
#   c = Crc32()                  tables made once (1 KB)
#   c.start(); c.feed(buf, i, n) bytes buf[i:i+n] into the running register
#   c.byte(b)                    one byte
#   c.low30(), c.low24()         the final CRC's low 30 / 24 bits (what a u32 field carries to
#                                the firmware -- msgtable's u32 keeps 30 bits -- / param_set's
#                                3-byte check)

from array import array


_TABLES = None  # (th, tl): made by the first Crc32 (not at import), shared by every one


def _make():
    # the table as two arrays of 16-bit halves (reflected poly 0xEDB88320).  A CRC table is
    # linear (T[a ^ b] = T[a] ^ T[b]): the 8 single-bit entries bit by bit, the rest by xor
    # (~300 steps instead of 2048: the board builds it at start-up, before the loop runs)
    th = array("H", [0] * 256)
    tl = array("H", [0] * 256)
    b = 1
    while b < 256:
        hi = 0
        lo = b
        for _ in range(8):
            if lo & 1:
                lo = ((lo >> 1) | ((hi & 1) << 15)) ^ 0x8320
                hi = (hi >> 1) ^ 0xEDB8
            else:
                lo = (lo >> 1) | ((hi & 1) << 15)
                hi = hi >> 1
        th[b] = hi
        tl[b] = lo
        b <<= 1
    for i in range(3, 256):
        low = i & -i
        if low != i:
            th[i] = th[low] ^ th[i ^ low]
            tl[i] = tl[low] ^ tl[i ^ low]
    return th, tl


class Crc32:
    def __init__(self):
        global _TABLES
        if _TABLES is None:
            _TABLES = _make()
        self.th = _TABLES[0]
        self.tl = _TABLES[1]
        self.hi = 0xFFFF
        self.lo = 0xFFFF

    def start(self):
        self.hi = 0xFFFF
        self.lo = 0xFFFF

    def byte(self, b):
        lo = self.lo
        hi = self.hi
        k = (lo ^ b) & 0xFF
        self.lo = ((lo >> 8) | ((hi & 0xFF) << 8)) ^ self.tl[k]
        self.hi = (hi >> 8) ^ self.th[k]

    def feed(self, buf, i, n):
        th = self.th
        tl = self.tl
        lo = self.lo
        hi = self.hi
        for j in range(i, i + n):
            k = (lo ^ buf[j]) & 0xFF
            lo = ((lo >> 8) | ((hi & 0xFF) << 8)) ^ tl[k]
            hi = (hi >> 8) ^ th[k]
        self.lo = lo
        self.hi = hi

    def low30(self):
        return (((self.hi ^ 0xFFFF) & 0x3FFF) << 16) | (self.lo ^ 0xFFFF)

    def low24(self):
        return (((self.hi ^ 0xFFFF) & 0xFF) << 16) | (self.lo ^ 0xFFFF)


def seal(layout, mid, vals, voff=0, raw=None, roff=0):
    # the trailing check of a msgtable.CHECKED command whose fields are vals[voff:] (host-side
    # tools and tests running on the firmware's codec; allocates): a u32 check is written into
    # vals, param_set's 3 raw bytes into raw[roff:] where its payload will be packed (pack
    # leaves raw fields alone); returns it.  0 (nothing written) for a message without one
    from . import msgtable as T
    if mid not in T.CHECKED:
        return 0
    n = layout.nfields[mid]
    pl = layout.plen[mid]
    buf = bytearray(pl)
    layout.pack(mid, vals, voff, buf, 0)
    w = 3 if mid == T.PARAM_SET else 4
    c = Crc32()
    c.byte(mid)
    c.feed(buf, 0, pl - w)
    if w == 3:
        v = c.low24()
        if raw is not None:
            o = roff + pl - 3
            raw[o] = v & 0xFF
            raw[o + 1] = (v >> 8) & 0xFF
            raw[o + 2] = v >> 16
        return v
    v = c.low30()
    vals[voff + n - 1] = v
    return v


def of(data, n=-1):
    # CRC-32 of data[:n] (all of it by default), low 30 bits (GAINS_COMMIT.check as the board
    # compares it; tools and tests; allocates a Crc32)
    c = Crc32()
    c.feed(data, 0, len(data) if n < 0 else n)
    return c.low30()
