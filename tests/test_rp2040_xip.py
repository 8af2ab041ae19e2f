"""The XIP flash-cache model of the emulated RP2040 (harness.mjs "XIP flash cache model"): misses
charged to the clock, the datasheet's aliases, two-way LRU sets, XIP_CTRL counters and flushes,
read from the board's own ``time.ticks_us`` and ``machine.mem32``."""

from __future__ import annotations

import pytest

from host.boards.rp2040.board import EmulatedBoard

pytestmark = pytest.mark.rp2040  # slow; skipped without the emulated board (tests/conftest.py)

N = 2000  # reads per loop: 2000 misses of 64 cycles = 1 ms, timed to 1 us
MISS = 64.0
# Time a loop of byte reads of the given addresses (bytecode; the loop's own code fits the cache
# and is identical between calls, so two calls differ only by the reads' misses; bytes, so that
# no value read is a heap-allocated big int).
SETUP = """
import time, machine
m = machine.mem8
r = machine.mem32
def t(a, b, c, n):
    for i in range(8):
        m[a]; m[b]; m[c]
    t0 = time.ticks_us()
    for i in range(n):
        m[a]; m[b]; m[c]
    return time.ticks_diff(time.ticks_us(), t0)
"""


@pytest.fixture(scope="module")
def board():
    with EmulatedBoard(main=False, xip_cache=True, xip_miss_cycles=MISS) as b:
        b.exec(SETUP)
        yield b


def _per_read_cycles(board: EmulatedBoard, slow: tuple[int, int, int], fast: tuple[int, int, int], misses: int) -> float:
    # extra cycles per expected miss of loop `slow` over loop `fast`
    a = int(board.exec(f"print(t({slow[0]}, {slow[1]}, {slow[2]}, {N}))"))
    b = int(board.exec(f"print(t({fast[0]}, {fast[1]}, {fast[2]}, {N}))"))
    return (a - b) * 125 / (misses * N)


BASE = 0x10000100  # inside the firmware image (any flash word reads the same way)
W = 0x2000  # 1024 sets x 8 bytes: addresses W apart share a set


def test_bypass_alias_misses_every_read_and_costs_the_penalty(board: EmulatedBoard) -> None:
    # 0x13: no check, no allocate -> each read is a flash read; 0x10 on a warm line is a hit
    cached = (BASE, BASE, BASE)
    per = _per_read_cycles(board, (BASE | 0x03000000, BASE, BASE), cached, 1)
    assert abs(per - MISS) < 1.5


def test_noalloc_alias_never_fills_and_nocache_alias_fills(board: EmulatedBoard) -> None:
    line = BASE + 0x40000  # a line nothing else reads
    noalloc = line | 0x01000000
    # 0x11 checks but does not allocate: a line only ever read through it misses every time
    assert abs(_per_read_cycles(board, (noalloc, BASE, BASE), (BASE, BASE, BASE), 1) - MISS) < 1.5
    # 0x12 does not check (always a flash read) but allocates: after it, 0x11 hits the line
    assert abs(_per_read_cycles(board, (line | 0x02000000, BASE, BASE), (BASE, BASE, BASE), 1) - MISS) < 1.5
    assert abs(_per_read_cycles(board, (line | 0x02000000, noalloc, BASE), (line | 0x02000000, BASE, BASE), 1)) < 1.5


def test_two_way_sets_with_lru(board: EmulatedBoard) -> None:
    a, b, c = BASE + 0x50000, BASE + 0x50000 + W, BASE + 0x50000 + 2 * W  # one set
    # two lines of a set stay (two ways); three in turn evict each other (LRU): 3 misses a round
    assert abs(_per_read_cycles(board, (a, b, c), (a, b, a), 3) - MISS) < 1.5
    # lines of different sets do not interfere
    assert abs(_per_read_cycles(board, (a, b, c + 8), (a, b, a), 1)) < 1.5


def test_counters_flush_and_switch(board: EmulatedBoard) -> None:
    out = board.exec(
        "r[0x1400000c] = 0\nr[0x14000010] = 0\nt(0x10000100, 0x10000100, 0x10000100, 100)\n"
        "h, a = r[0x1400000c], r[0x14000010]\nprint(h, a, r[0x14000000] & 1, r[0x14000008] & 1)")
    hit, acc, en, ready = map(int, out.split())
    assert en == 1 and ready == 1
    assert 300 <= hit <= acc and hit > 0.9 * acc  # the reads and the loop's code, nearly all hits
    st0 = board.xip_stats()
    board.exec("r[0x14000004] = 1")  # FLUSH
    st1 = board.xip_stats()
    assert st1["flushes"] == st0["flushes"] + 1
    # a flash write (LittleFS through the ROM's flash_range_program) flushes too
    board.exec("f = open('xip.txt', 'w')\nf.write('x' * 600)\nf.close()")
    assert board.xip_stats()["flushes"] > st1["flushes"]
    # switched off: flash reads cost what RAM reads cost
    board.xip_config(on=False)
    try:
        assert abs(_per_read_cycles(board, (BASE | 0x03000000, BASE, BASE), (BASE, BASE, BASE), 1)) < 1.5
    finally:
        board.xip_config(on=True)


def test_perf_bench_import_matches_the_real_pico_only_with_the_model(board: EmulatedBoard) -> None:
    # MicroPython's core_import_mpy_single (scored as run-perfbench.py scores it) against the
    # real Pico's published score (host/bench/rp2040_perfbench_published.toml): the ideal
    # emulator is optimistic by 1.37x (an .mpy import touches much cold flash code), the
    # model within 10 % (measured 0.93); the full table is `make bench` rp2040_calibration
    from host.bench.rp2040_calibration import PERF_BENCH, load_published, run_suite

    test = PERF_BENCH / "core_import_mpy_single.py"
    if not test.is_file():
        pytest.skip("perf_bench not unpacked (make rp2040)")
    real = load_published()["pr12846"]["scores"][test.name]
    with_model = run_suite(board, [test])[0]
    board.xip_config(on=False)
    try:
        ideal = run_suite(board, [test])[0]
    finally:
        board.xip_config(on=True)
    assert with_model.score is not None and ideal.score is not None, (with_model, ideal)
    assert abs(with_model.score / real - 1) <= 0.10
    assert ideal.score / real > 1.2
