# CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, refin/refout false, xorout 0;
# check value of b"123456789" is 0x29B1).  Table-driven, allocation-free once the
# table exists; make_table() is called once at start-up by the codec objects.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from array import array

INIT = const(0xFFFF)
_POLY = const(0x1021)


_table = None


def make_table():
    # 256-entry lookup table, built once and shared (read-only; ~19 ms of bytecode on an RP2040)
    global _table
    if _table is not None:
        return _table
    t = array("H", bytes(512))
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ _POLY) if c & 0x8000 else (c << 1)
        t[i] = c & 0xFFFF
    _table = t
    return t


def update(table, crc, b):
    # one byte into the running crc
    return ((crc << 8) & 0xFFFF) ^ table[((crc >> 8) ^ b) & 0xFF]


def compute(table, buf, start, end, crc=INIT):
    # crc over buf[start:end]; allocation-free
    for i in range(start, end):
        crc = ((crc << 8) & 0xFFFF) ^ table[((crc >> 8) ^ buf[i]) & 0xFF]
    return crc
