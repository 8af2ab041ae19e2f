"""Tick arithmetic of firmware/fixmath.py: time.ticks_* semantics, no big ints on 32 bits.

MicroPython's tick counters have a period of 2**30, and 2**30 is not a small int on a
32-bit port: ``d - 2**30`` or ``(t + 1) & (2**30 - 1)`` at the wrap allocate a big int on
every call that reaches it (App.run() calls ticks_diff twice a tick, and a negative
difference every tick).  Under the 32-bit WebAssembly port, ticks_diff, ticks_add and
ticks_next over random pairs and every wrap edge allocate 0 bytes and equal the port's
own time.ticks_diff / time.ticks_add; the old formula, run the same way, allocates (the
check is real).  The same values are checked against the reference formula here.
"""

from __future__ import annotations

import random

import pytest

from firmware.fixmath import ticks_add, ticks_diff, ticks_next
import fwharness as H

PERIOD = 1 << 30
MASK = PERIOD - 1
HALF = PERIOD >> 1
EDGES = [0, 1, 2, 1000, HALF - 2, HALF - 1, HALF, HALF + 1, MASK - 1000, MASK - 1, MASK]
DEDGES = [0, 1, -1, 2, -2, 20000, -20000, HALF - 1, -(HALF - 1), HALF >> 1, -(HALF >> 1)]


def ref_diff(a: int, b: int) -> int:
    # time.ticks_diff(a, b) of MicroPython (extmod/modtime.c)
    return ((a - b + HALF) & MASK) - HALF


def ref_add(t: int, d: int) -> int:
    return (t + d) & MASK


def _cases(n: int = 3000, seed: int = 7) -> tuple[list[int], list[int], list[int]]:
    rng = random.Random(seed)
    a = [x for x in EDGES for _ in EDGES]
    b = [y for _ in EDGES for y in EDGES]
    d = [DEDGES[i % len(DEDGES)] for i in range(len(a))]
    for _ in range(n):
        x = rng.randrange(PERIOD)
        # near pairs (negative and positive small differences, across the wrap) and far ones
        y = (x + rng.randrange(-5000, 5000)) & MASK if rng.random() < 0.5 else rng.randrange(PERIOD)
        a.append(x)
        b.append(y)
        d.append(rng.randrange(-(HALF - 1), HALF))
    return a, b, d


def test_reference_semantics_cpython() -> None:
    a, b, d = _cases()
    for x, y, z in zip(a, b, d):
        assert ticks_diff(x, y) == ref_diff(x, y), (x, y)
        assert ticks_add(x, z) == ref_add(x, z), (x, z)
        assert -HALF <= ticks_diff(x, y) < HALF
    assert [ticks_next(x) for x in EDGES] == [(x + 1) & MASK for x in EDGES]
    assert ticks_diff(0, MASK) == 1 and ticks_diff(MASK, 0) == -1
    assert ticks_diff(HALF, 0) == -HALF  # the half period is negative, as in MicroPython


def test_clocks_with_a_longer_period_cpython() -> None:
    # the 64-bit unix port's time.ticks_us has period 2**62: values above 2**30 must give
    # the same results mod 2**30 (the HIL main and App.run pace on it)
    a, b, d = _cases(500)
    for x, y, z in zip(a, b, d):
        for hi in (1, 5, 1 << 31):
            assert ticks_add(x + hi * PERIOD, z) == ref_add(x, z)
            assert ticks_diff(x + hi * PERIOD, y) == ticks_diff(x, y + 3 * PERIOD) == ref_diff(x, y)


SCRIPT = H.INTS_SRC + """
import time
from firmware.fixmath import ticks_add, ticks_diff, ticks_next


A = ints(%(a)r)
B = ints(%(b)r)
D = ints(%(d)r)
n = len(A)
R = array('i', [0] * n)
S = array('i', [0] * n)
X = array('i', [0] * n)
P = 0x40000000  # the old formula's constant (a big int here)
d = 0
i = 0


def diffs():
    for i in range(n):
        R[i] = ticks_diff(A[i], B[i])


def adds():
    for i in range(n):
        S[i] = ticks_add(A[i], D[i])


def nexts():
    for i in range(n):
        X[i] = ticks_next(A[i])


def old():
    # the replaced ticks_diff: d - 2**30 for the upper half
    for i in range(n):
        d = (A[i] - B[i]) & 0x3FFFFFFF
        if d >= 0x20000000:
            d -= P


""" + H.WASM_ALLOC_RUN + """
run('diff', diffs)
run('add', adds)
run('next', nexts)
run('old', old)
bad = 0
for i in range(n):
    if R[i] != time.ticks_diff(A[i], B[i]):
        bad += 1
    if S[i] != time.ticks_add(A[i], D[i]):
        bad += 1
    if X[i] != time.ticks_add(A[i], 1):
        bad += 1
print('mismatch', bad)
print('n', n)
print('period', time.ticks_add(0x3FFFFFFF, 1))
print('R', ' '.join(str(v) for v in R))
"""


@pytest.mark.interps("wasm", "rp2040")
def test_no_big_ints_and_time_semantics_on_32bit_ports(interp) -> None:
    # the 32-bit WebAssembly port and the emulated Pico (MicroPython's rp2 port: the board's own
    # time.ticks_*), each against its own clock functions; the allocation probe is gc.mem_alloc's.
    # The board takes 300 random pairs besides the edges' 121: its REPL board is shared by the
    # session's tests, and after them its heap had no 8.5 kB block for 1000 pairs' arrays (with
    # 3000, a 30 kB allocation failed on a fresh one)
    a, b, d = _cases(300 if interp.name == "rp2040" else 3000)
    code = SCRIPT % {"a": " ".join(map(str, a)), "b": " ".join(map(str, b)), "d": " ".join(map(str, d))}
    out = {}
    for line in interp.run(code, timeout=300).splitlines():
        k, _, v = line.partition(" ")
        out[k] = v
    assert int(out["n"]) == len(a)
    assert int(out["period"]) == 0  # the port's ticks period is 2**30, as on the RP2040
    assert int(out["diff"]) == 0 and int(out["add"]) == 0 and int(out["next"]) == 0, out
    assert int(out["old"]) > 1000  # the old formula allocates: the measurement sees it
    assert int(out["mismatch"]) == 0
    assert [int(v) for v in out["R"].split()] == [ref_diff(x, y) for x, y in zip(a, b)]
