# The arming token's seed (App config "seed"; msgtable SESSION): different at every start of a
# board, even where os.urandom is the same at every power-up (an emulated RP2040 starts from the
# same state each time).  Mixed from what differs: a seed persisted across starts (the file
# below, rewritten at every start: a reset never starts from the same value twice), os.urandom
# (on the rp2 port: bits of the RP2040's ring oscillator, ROSC RANDOMBIT -- which rp2040js
# emulates as the same sequence at every power-up: every emulated boot drew arming epoch 42)
# and the microsecond clock.
# Start-up only (it allocates and writes the flash, like boot.boot_count).

_SEED_FILE = "session_seed"
_MASK = 0x3FFFFFFF


def _mix(v, x):
    # fold x (< 2**30) into v (< 2**30): xor, then an odd multiplier in 15-bit limbs (small ints)
    v = (v ^ x) & _MASK
    hi = v >> 15
    lo = v & 0x7FFF
    t = 0x4E6D * lo
    m = ((0x038C * lo) & 0x7FFF) + ((0x4E6D * hi) & 0x7FFF)
    s = (t & 0x7FFF) + 0x3039
    return ((((t >> 15) + m + (s >> 15)) & 0x7FFF) << 15) | (s & 0x7FFF)


def seed(path=_SEED_FILE):
    v = 0
    try:
        with open(path) as f:
            v = int(f.read()) & _MASK
    except (OSError, ValueError):
        v = 0
    try:
        import os
        b = os.urandom(4)
        v = _mix(v, ((b[0] & 0x3F) << 24) | (b[1] << 16) | (b[2] << 8) | b[3])
    except (ImportError, AttributeError, OSError):
        pass
    try:
        import time
        v = _mix(v, time.ticks_us() & _MASK)
    except (ImportError, AttributeError):
        pass
    v = _mix(v, 1)
    try:
        with open(path, "w") as f:
            f.write(str(v))
    except OSError:
        pass
    return v
