# Small-int fixed-point helpers shared by the firmware modules.
#
# Every value handled here stays inside the 31-bit small-int range of a 32-bit
# MicroPython (-2**30 .. 2**30-1): results saturate, they never wrap or grow.
# The hot path (controller.step) inlines these for speed; the functions are for
# the colder paths (conversions, parameter handling, table parsing).

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from array import array

SMALL_MAX = const(0x3FFFFFFF)
SMALL_MIN = const(-0x40000000)
_TICKS_MASK = const(0x3FFFFFFF)
_TICKS_HALF = const(0x20000000)
_TICKS_PERIOD = const(0x40000000)


def clamp(v, lim):
    # saturate v to [-lim, lim]
    if v > lim:
        return lim
    if v < -lim:
        return -lim
    return v


def rshift(acc, s):
    # acc / 2**s rounded half up (arithmetic shift); s >= 0
    if s <= 0:
        return acc
    return (acc + (1 << (s - 1))) >> s


def ticks_diff(a, b):
    # a - b for tick counters that wrap at a multiple of 2**30 (time.ticks_us on every
    # port); the result is in -2**29 .. 2**29-1
    d = (a - b) & _TICKS_MASK
    if d >= _TICKS_HALF:
        d -= _TICKS_PERIOD
    return d


def s32_le(buf, i):
    # signed little-endian int32 at buf[i:i+4], or None if outside the small-int range
    # (|v| >= 2**30): checked on the top byte before any arithmetic, so nothing grows
    top = buf[i + 3]
    if top >= 128:
        top -= 256
    if top > 63 or top < -64:
        return None
    return top * 16777216 + (buf[i + 2] << 16) + (buf[i + 1] << 8) + buf[i]


def bound_units(g, b):
    # |g| * b in units of 1024, rounded up (a conservative bound), computed without
    # ever leaving the small-int range; g, b >= 0 and < 2**20 (the caller checks)
    return g * (b >> 10) + ((g * (b & 1023) + 1023) >> 10)


def zeros(n, typecode="i"):
    # a zero-filled array of n entries (start-up only: builds a temporary list)
    return array(typecode, [0] * n)
