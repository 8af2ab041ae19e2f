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
# tick counters: period 2**30 (time.ticks_us on every port), wrapped values 0 .. 2**30-1.
# 2**30 itself is no small int on a 32-bit port: no expression here may compute it
_TICKS_MASK = const(0x3FFFFFFF)
_TICKS_HALF = const(0x20000000)
_TICKS_HIGH = const(~0x3FFFFFFF)  # -2**30: every bit from 30 up set


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
    # a - b for tick counters a, b in 0 .. 2**30-1 (time.ticks_diff(a, b)), or from any
    # clock whose period is a multiple of 2**30; the result is in -2**29 .. 2**29-1.
    # On 32 bits, a - b is in -(2**30-1) .. 2**30-1 and the masked value in
    # 0 .. 2**30-1; a value of the upper half becomes negative by setting the bits from
    # 30 up (= d - 2**30), so nothing leaves the small-int range of a 32-bit port
    d = (a - b) & _TICKS_MASK
    if d >= _TICKS_HALF:
        d |= _TICKS_HIGH
    return d


def ticks_add(t, d):
    # t + d wrapped to 0 .. 2**30-1 (time.ticks_add(t, d) on a 32-bit port) for |d| <
    # 2**29; the sum is compared before it is formed, so it never reaches 2**30.  t is
    # masked first: a clock whose period is a larger multiple of 2**30 (time.ticks_us of
    # the 64-bit unix port: 2**62) gives the same result mod 2**30, as ticks_diff reads it
    t &= _TICKS_MASK
    if d >= 0:
        if t > _TICKS_MASK - d:
            return t - (_TICKS_MASK - d) - 1
        return t + d
    if t < -d:
        return t + d + _TICKS_MASK + 1
    return t + d


def ticks_next(t):
    # t + 1 wrapped to 0 .. 2**30-1 (tick and uptime counters)
    if t < _TICKS_MASK:
        return t + 1
    return 0


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
