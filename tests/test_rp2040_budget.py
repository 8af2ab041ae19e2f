"""What only the board runs, measured on the emulated RP2040: the paced loop (App.run with the
serial link on machine.UART and the real HalPico) allocates nothing per tick; the heap-locked
loop does not latch its allocation fault; the encoder read returns in bounded time while the
PIO pushes continuously; the whole loop iteration within a generous per-tick bound (mean
< 30 % of the period, none over 70 % once the flash cache is warm, none late before; the
<= 500 us and <= 70 % targets are `make bench` figures, host/bench/rp2040.py, not tests).
Timed with the harness's XIP flash-cache model on (``xip_cache=True``): the cycles a real Pico
is predicted to take (docs/firmware.md, "Board timing"), not the ideal ones.

A user hook (``SerialLink.set_user``) runs in the spare time within its budget and a slow one is
switched off after one call; while it runs, its guard timer runs each step that comes due on
time (no late tick).  One board (REPL, bundle importable) shared by the module; about
35-45 s of wall time.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from firmware.supervisor import F_LOOP
from host.boards.rp2040.board import EmulatedBoard, build_bundle
from host.link import messages as M
from sim.params import load_params

pytestmark = pytest.mark.rp2040  # slow; skipped without the emulated board (tests/conftest.py)

# what main.py builds, with the command watchdog relaxed (the test feeds no keep-alive) and
# telemetry every tick (the link's worst case) unless told
SETUP = """
import gc, time, machine
import firmware.board as B
from firmware.hal_pico import HalPico
from firmware.app import App
from firmware.link_serial import SerialLink
hal = HalPico(B)
uart = hal.uart()
app = None


def mk(telem_div=1):
    # a fresh App on the real HAL and link, as main.py builds it
    global app
    cfg = B.config()
    cfg['watchdog_ms'] = 10000
    cfg['telem_div'] = telem_div
    cfg['epoch'] = 0  # the arming epoch the scripted ARM frames carry
    app = App(hal, config=cfg)
    app.set_link(SerialLink(uart, app))
"""

CHUNK = """
gc.collect()
gc.disable()
a = gc.mem_alloc()
app.run(n={n}, lock=False)
d = gc.mem_alloc() - a
gc.enable()
print(d, app.sup.state, app.sup.faults)
"""


WARMUP = 6  # loop iterations the flash cache takes to hold the loop's code again (measured: 3)


def _frames(*msgs: M.Message) -> bytes:
    return b"".join(M.encode_serial(m, i) for i, m in enumerate(msgs))


@pytest.fixture(scope="module")
def board(tmp_path_factory: pytest.TempPathFactory):
    bundle = build_bundle(tmp_path_factory.mktemp("bundle"))
    with EmulatedBoard(bundle, main=False, xip_cache=True) as b:
        b.set_adc(int(round(load_params().pot_offset)))  # upright: the loop balances
        b.exec(SETUP, timeout=5.0)
        yield b


def test_paced_loop_with_the_uart_link_allocates_nothing_per_tick(board: EmulatedBoard) -> None:
    # a fresh App; its first step() allocates once (48 B on MicroPython 1.25 with the heap
    # unlocked: not per tick; locked, the first tick does not fault -- next test); each run()
    # call allocates a fixed amount at its start and end (watchdog, reset mark); then
    # commands arrive during the first measured chunk (arm, reference, requests: parsed,
    # dispatched, answered) and telemetry goes out every tick of every chunk
    board.exec("mk()\napp.run(n=2, lock=False)", timeout=2.0)
    # what one call of App.run allocates whatever its length, outside the tick: it starts the
    # hardware watchdog (machine.WDT and its bound feed, 32 B), marks the reset cause (16 B)
    # and, bounded, stops the watchdog again (16 B) -- 64 B on MicroPython 1.25.  main.py calls
    # run() once; a chunk of n ticks must allocate exactly this, i.e. nothing per tick
    once = int(board.exec(CHUNK.format(n=1), timeout=3.0).split()[0])
    assert once <= 64, f"one App.run call (start/stop, no ticks but one) allocates {once} B"
    board.uart_write(_frames(M.BY_NAME["arm"](epoch=0), M.BY_NAME["set_reference"](x_um=20000),
                             M.BY_NAME["request"](msg_id=M.BY_NAME["timing"].ID),
                             M.BY_NAME["param_get"](index=0)))
    deltas = []
    for _ in range(3):
        d, state, faults = (int(v) for v in board.exec(CHUNK.format(n=100), timeout=3.0).split())
        deltas.append(d)
    assert deltas == [once] * 3, f"bytes allocated by 100 ticks of App.run, per chunk (1 tick: {once} B)"
    assert state == 2 and faults == 0  # balancing throughout, no fault


def test_heap_locked_loop_does_not_latch_its_allocation_fault(board: EmulatedBoard) -> None:
    # locked from the first tick of a fresh App, as main.py runs it
    board.uart_write(_frames(M.BY_NAME["arm"](epoch=0), M.BY_NAME["set_reference"](x_um=-10000)))
    out = board.exec("mk()\napp.run(n=200)\nprint(app.sup.state, app.sup.faults)", timeout=3.0)
    state, faults = (int(v) for v in out.split())
    assert not faults & F_LOOP, f"F_LOOP latched (faults={faults:#x})"
    assert state == 2


def test_encoder_read_is_bounded_while_the_pio_pushes(board: EmulatedBoard) -> None:
    # the PIO pushes the count on every sampling pass; the edges of a moving encoder arrive
    # during the reads
    code = ("mx = 0\nt = time.ticks_us\nfor i in range(300):\n"
            "    t0 = t()\n    v = hal.read_encoder()\n    dt = time.ticks_diff(t(), t0)\n"
            "    if dt > mx:\n        mx = dt\nprint(mx, v)")
    start = int(board.exec("print(hal.read_encoder())", timeout=0.5))
    board.set_encoder(start + 300)
    mx, v = (int(x) for x in board.exec(code, timeout=1.0).split())
    assert mx < 150, f"one read_encoder() took {mx} us"
    board.run(2000)
    assert int(board.exec("print(hal.read_encoder())", timeout=0.5)) == (start + 300) & 0xFFFF


def _loop_within_the_budget(board: EmulatedBoard, setup: str) -> None:
    # a fresh App (setup: its code), armed, 250 ticks timed by the loop probe, then 250 more;
    # asserted as the next test says
    board.exec(setup, timeout=2.0)
    board.uart_write(_frames(M.BY_NAME["arm"](epoch=0)))
    board.loop_probe(gap_us=50.0)
    board.loop_iters.clear()
    out = board.exec("app.run(n=250)\nprint(app.sup.state, app.timing.overruns, app.n_late, app.period_us)", timeout=3.0)
    board.loop_probe(False)
    state, overruns, late, period = (int(v) for v in out.split())
    # the probe's first iterations run from the exec's start (the REPL compiling the code),
    # not from a wait of the loop: dropped, as host/bench/rp2040.py does; so is the last (it
    # runs on into run()'s return to the REPL)
    it = np.array([(e - s) / 125.0 for s, e in board.loop_iters])[2:-1]
    assert it.size >= 200, out
    assert state == 2 and period == 2000, out
    # the first ticks run on a cold flash cache (the REPL's compile evicted the loop's code):
    # on a real board too, so they must fit the period, but the 70 % budget is the warm one
    warm, cold = it[WARMUP:], it[:WARMUP]
    assert 100.0 < warm.mean() < 0.3 * period, f"mean loop iteration {warm.mean():.0f} us"
    assert warm.max() < 0.7 * period, f"longest loop iteration {warm.max():.0f} us"
    # relaxed from one period to the firmware's own late-tick threshold (1.5 periods) when the
    # arming token's CRC-32 check and the session code (issue 23) joined the cold working set: the
    # tick that handles the first arm on a cold cache measured 2520 us predicted (1850 before);
    # the firmware's clock below must still see no late tick
    assert cold.max() < 1.5 * period, f"first iterations {np.round(cold)} us"
    # that cold arming tick is the one late tick the firmware's clock may have seen (relaxed from
    # none, same reason); a second run (balancing already, its first tick again after the REPL's
    # compile: at most one more overrun) sees no late tick at all
    assert overruns <= 1 and late <= 1, out
    out2 = board.exec("app.run(n=250)\nprint(app.sup.state, app.timing.overruns, app.n_late)", timeout=3.0)
    state2, overruns2, late2 = (int(v) for v in out2.split())
    assert state2 == 2 and overruns2 - overruns <= 1 and late2 == late, (out, out2)


def test_whole_loop_iteration_within_a_generous_budget(board: EmulatedBoard) -> None:
    # with main.py's telemetry rate (every 10th tick), arming and balancing: measured 436 us
    # mean, 893 us max with the telemetry pair in ideal cycles (the viper emitter's fused
    # step, issue 12; it was 768 / 1252 us before the slot arrays); predicted for a real Pico
    # (XIP cache model): about 575 us mean, 1130 us max once warm, 1850 us for the first
    # ticks after the REPL's compile left the flash cache cold.  `make bench` prints the
    # figures and the <= 500 us / <= 70 % targets.  Generous for code added later, tight
    # enough to catch the step losing its slot arrays: the mean within 30 % of the 2 ms period
    # (600 us), no warm iteration over 70 % (emulated cycles: the host's load does not change
    # them), the cold first ticks within the period, and the firmware's own clock saw no late
    # tick and no overrun
    _loop_within_the_budget(board, "mk(10)")


def test_whole_loop_iteration_with_the_gear_play_model_within_the_same_budget(board: EmulatedBoard) -> None:
    # the same bounds with the board parameters `upright commission` sets for a robot with 1 mm
    # of gear play and 0.2 N of Coulomb friction (drive_params): the step's gap model and the
    # compensation's push run every tick (the shipped configuration leaves that branch off).
    # The mean was 613 us (max 1254) while the step called its wheel-side correction as a
    # bytecode method from the viper code (~78 us a tick); written out in the step since: 535 /
    # 1196 us (shipped 526 / 1187; tests/test_link_budget_rp2040.py for the link's side)
    from firmware import msgtable as T
    from firmware.controller import LIM_GHB
    from fwharness import play_robot

    _, bp = play_robot()
    gp, fc = bp[T.P_GEAR_PLAY], bp[T.P_CART_COULOMB]
    assert gp > 0 and fc > 0, bp
    setup = f"mk(10)\nprint(app.param_set({T.P_GEAR_PLAY}, {gp}), app.param_set({T.P_CART_COULOMB}, {fc}))"
    assert board.exec(setup, timeout=2.0).split() == [str(T.OK)] * 2
    got = board.exec(f"print(app.params[{T.P_GEAR_PLAY}], app.params[{T.P_CART_COULOMB}], app.ctrl.lim[{LIM_GHB}] > 0)",
                     timeout=1.0).split()
    assert got == [str(gp), str(fc), "True"], got
    _loop_within_the_budget(board, "pass")


HOOKS = """
from array import array
cnt = array('i', [0])
def good():
    # a user's small job: allocation-free, well inside its budget
    cnt[0] += 1
def slow():
    # a user's job that breaks its 200 us budget: 5 ms of busy waiting
    t = time.ticks_us()
    while time.ticks_diff(time.ticks_us(), t) < 5000:
        pass
def sleepy():
    # ... and one that sleeps 5 ms in one C call (time.sleep_us serves the port's events)
    time.sleep_us(5000)
def stats():
    L = app.link
    print(L.user_runs, L.user_over, cnt[0], app.timing.overruns, app.n_late, app.sup.state, L.adm.n_taken)
def counts():
    return app.timing.overruns, app.n_late, app.link.adm.n_taken
"""


def test_user_hook_runs_in_the_spare_time_and_a_slow_one_is_switched_off(board: EmulatedBoard) -> None:
    # SerialLink.set_user (docs/firmware.md, "User code in the spare time"): a hook within its
    # budget runs every tick it fits, the loop keeps every deadline; a hook that takes 5 ms on a
    # 200 us budget runs once and is switched off -- and while it runs, its guard timer
    # (HalPico.guard_timer, admit.Admit.take) runs each step whose deadline comes on time, so it
    # makes no tick late (before the guard it cost one late tick: MicroPython cannot stop it)
    board.exec(HOOKS, timeout=3.0)
    board.exec("mk(10)", timeout=2.0)
    board.uart_write(_frames(M.BY_NAME["arm"](epoch=0)))
    board.exec("app.run(n=60)", timeout=3.0)  # armed, balancing, the cold first ticks behind
    runs0, over0, _, ov0, late0, _, taken0 = (int(v) for v in board.exec("stats()", timeout=2.0).split())
    out = board.exec("app.link.set_user(good, 200)\napp.run(n=200)\nstats()", timeout=4.0)
    runs, over, cnt, ov, late, state, taken = (int(v) for v in out.splitlines()[-1].split())
    assert state == 2 and over == 0 and taken == taken0, out
    assert runs - runs0 == cnt and cnt >= 150, out  # nearly every tick had the spare time (measured: 200 of 200)
    # the run's first tick follows the REPL's compile (a cold cache: at most one overrun, as in
    # test_whole_loop_iteration_within_a_generous_budget); none from the hook
    assert ov - ov0 <= 1 and late - late0 <= 1, out
    # the slow hook, set between two runs of one exec (the loop's code warm: no cold first tick;
    # the pause between the runs is one on purpose, not a period: Timing.restart, as App.run's
    # own pauses)
    out = board.exec("app.link.set_user(None, 0)\napp.run(n=30)\napp.link.set_user(slow, 200)\n"
                     "app.timing.restart()\nc1 = counts()\napp.run(n=100)\nprint(*c1)\nstats()", timeout=4.0)
    ov1, late1, taken1 = (int(v) for v in out.splitlines()[-2].split())
    runs2, over2, _, ov2, late2, state2, taken2 = (int(v) for v in out.splitlines()[-1].split())
    assert over2 == 1 and runs2 == runs + 1, out  # one call, then off
    assert state2 == 2, out  # still balancing
    # 5 ms past a tick's spare time: the next two deadlines came while it ran, the guard ran both
    assert taken2 - taken1 >= 2, out
    assert late2 == late1 and ov2 == ov1, out  # no late tick, no overrun
    out = board.exec("app.link.set_user(sleepy, 200)\napp.timing.restart()\nc1 = counts()\napp.run(n=100)\n"
                     "print(*c1)\nstats()", timeout=4.0)
    ov1, late1, taken1 = (int(v) for v in out.splitlines()[-2].split())
    runs3, over3, _, ov3, late3, state3, taken3 = (int(v) for v in out.splitlines()[-1].split())
    assert over3 == 2 and runs3 == runs2 + 1 and state3 == 2, out
    assert taken3 - taken1 >= 2 and late3 == late1 and ov3 == ov1, out


def test_the_per_part_figures_hold_over_heap_layouts() -> None:
    # make bench's heap-layout rows (host.bench.rp2040._layouts): two fresh boards, the second
    # with 48 bytes allocated before the firmware's imports (its .mpy code and the App's objects
    # at other addresses). Every part is timed under both; app.step is the same within 5 % (seen:
    # within 0.2 %; what moves the figures between builds is the C code's place in flash)
    from host.bench.rp2040 import PARTS, _layouts

    lay = _layouts("viper", pads=(0, 48), n=20)
    assert set(lay) == set(PARTS) and all(len(v) == 2 and min(v) > 0 for v in lay.values()), lay
    a, b = lay["app.step"]
    assert abs(a - b) <= 0.05 * min(a, b), lay
    assert max(lay["app.step"]) < 0.3 * 2000, lay
