"""The firmware's identification excitation (EXCITE, firmware/excite.py; issue 15 item 4).

Under CPython and the MicroPython unix port, the real App with a scripted HAL: the PRBS is
maximum-length and balanced; EXCITE starts only while balancing and within half the force
clamp; mode 1 adds +-amp to the controller's force (the predictor's buffer holds the sum),
never beyond the clamp; mode 2 drives open loop; telemetry then carries the sensors and the
applied force; disarm and faults stop it; a tick with the excitation allocates nothing
(heap locked on the unix port).
"""

from __future__ import annotations

import pytest

from firmware import msgtable as T
from firmware.excite import Excite
import fwharness as H
from host.boards.mpyrun import run_unix


def test_prbs_is_maximum_length_and_balanced() -> None:
    ex = Excite()
    assert ex.start(T.EXC_ADD, 1000, 1, 0, 4) == T.OK
    ex.amp = 1
    seq = [ex.next() for _ in range(2 * 32767)]
    assert seq[:32767] == seq[32767:]
    # period exactly 32767 (not a divisor of it: 7 * 31 * 151)
    for p in (7, 31, 151, 217, 1057, 4681):
        assert seq[:p] != seq[p:2 * p]
    assert abs(sum(seq[:32767])) == 1  # 16384 ones, 16383 zeros
    ex2 = Excite()
    ex2.start(T.EXC_OPEN, 1000, 5, 0, 4)
    ex2.amp = 1
    held = [ex2.next() for _ in range(50)]
    assert all(held[i] == held[i - i % 5] for i in range(50))
    assert held[:50:5] == seq[:10]


def test_start_checks() -> None:
    ex = Excite()
    assert ex.start(3, 100, 1, 9, 1370) == T.R_OUT_OF_RANGE
    assert ex.start(T.EXC_ADD, 100, 0, 9, 1370) == T.R_OUT_OF_RANGE
    assert ex.start(T.EXC_ADD, 0, 1, 9, 1370) == T.R_OUT_OF_RANGE
    # 2 N = 1024 LSB at 2**-9 N > half of a 1370 LSB clamp
    assert ex.start(T.EXC_ADD, 2000, 1, 9, 1370) == T.R_OUT_OF_RANGE
    assert ex.start(T.EXC_ADD, 1000, 1, 9, 1370) == T.OK and ex.amp == 512 and ex.on == 1
    assert ex.start(T.EXC_OFF, 0, 0, 0, 0) == T.OK and ex.mode == 0 and ex.on == 0


APP_SCRIPT = H.FAKE_HAL + """
from firmware.app import App
from firmware import msgtable as T
from array import array
try:
    from micropython import heap_lock, heap_unlock
except ImportError:
    heap_lock = heap_unlock = None
hal = Hal()
app = App(hal, config={'watchdog_ms': 0, 'stall_ms': 0})
c = app.ctrl
tel = array('i', [0] * 8)
out = []
out.append(app.cmd_excite(1, 500, 4))          # disarmed: refused
app.step()
app.cmd_arm()
for k in range(5):
    app.step()
out.append(app.sup.state)
out.append(app.cmd_excite(1, 100000 // 10, 4))  # beyond half the clamp
out.append(app.cmd_excite(1, 500, 4))
amp = app.exc.amp
ok = 1
sat = 0
for k in range(400):
    hal.adc = 2048 + ((k * 7) % 21) - 10
    hal.enc = k % 40 if (k // 40) % 2 == 0 else 40 - k % 40
    if heap_lock:
        heap_lock()
    # the controller's own force for the same tick, then the tick with the excitation
    app.step()
    if heap_lock:
        heap_unlock()
    e = app.exc.amp if app.exc.lfsr & 1 else -app.exc.amp
    raw = c.u_raw if -c.ulim <= c.u_raw <= c.ulim else (c.ulim if c.u_raw > 0 else -c.ulim)
    want = raw + e
    want = c.ulim if want > c.ulim else (-c.ulim if want < -c.ulim else want)
    if c.u != want or c.b[c.d - 1] != want:
        ok = 0
    if want in (c.ulim, -c.ulim):
        sat += 1
    app.fill_telemetry(tel)
    s = app.sensors
    if tel[0] != app._tel(s.yx, 0) or tel[2] != app._tel(s.yp, 2) or tel[5] != app._tel(c.u, 4):
        ok = 0
out.append(ok)
out.append(amp)
out.append(app.sup.state)
# open loop: the force is the excitation alone
out.append(app.cmd_excite(2, 500, 1))
ok2 = 1
for k in range(50):
    app.step()
    e = app.exc.amp if app.exc.lfsr & 1 else -app.exc.amp
    if c.u != e or app.duty != app.motor.duty(e, 0):
        ok2 = 0
out.append(ok2)
app.cmd_disarm()
app.step()
out.append(app.exc.on)
out.append(app.exc.mode)
out.append(app.duty)
out.append(app.cmd_excite(0, 0, 0))
out.append(app.exc.mode)
print(' '.join(str(v) for v in out))
"""


def _check(vals: list[int]) -> None:
    refused, state, too_big, started, ok, amp, state2, started2, ok2, on, mode, duty, stopped, mode2 = vals
    assert refused == T.R_BAD_STATE
    assert state == 2  # balancing
    assert too_big == T.R_OUT_OF_RANGE
    assert started == T.OK and amp > 0
    assert ok == 1, "force != clamp(controller + excitation), buffer or telemetry wrong"
    assert state2 == 2, "no longer balancing after the excited ticks"
    assert started2 == T.OK and ok2 == 1
    assert on == 0 and mode == 2 and duty == 0  # disarm stops the signal, the telemetry mode stays
    assert stopped == T.OK and mode2 == 0


def test_app_excitation_cpython() -> None:
    _check([int(v) for v in H.run_cpython(APP_SCRIPT).split()])


def test_app_excitation_micropython_heap_locked() -> None:
    out = run_unix(APP_SCRIPT)
    _check([int(v) for v in out.split()])


@pytest.mark.parametrize("mode", [1, 2])
def test_fault_stops_excitation(mode: int) -> None:
    ns: dict = {}
    exec(compile(H.FAKE_HAL, "<hal>", "exec"), ns)
    from firmware.app import App

    hal = ns["Hal"]()
    app = App(hal, config={"watchdog_ms": 0, "stall_ms": 0})
    app.step()
    app.cmd_arm()
    app.step()
    assert app.cmd_excite(mode, 300, 2) == T.OK and app.exc.on == 1
    for _ in range(10):
        app.step()
    hal.adc = 2048 + 900  # far beyond the tilt limit: the supervisor latches a fault
    app.step()
    assert app.sup.faults & 1 and app.sup.state == 3
    assert app.exc.on == 0 and app.duty == 0
    # it does not restart by itself after clear_faults and a new arm
    hal.adc = 2048
    app.step()
    app.cmd_clear_faults()
    app.cmd_arm()
    for _ in range(5):
        app.step()
    assert app.sup.state == 2 and app.exc.on == 0


WASM_SCRIPT = H.FAKE_HAL + H.WASM_ALLOC_RUN + """
from array import array
from firmware.app import App
hal = Hal()
app = App(hal, config={'watchdog_ms': 0, 'stall_ms': 0})
tel = array('i', [0] * 8)
app.step()
app.cmd_arm()
for k in range(5):
    app.step()
# the largest amplitude the board takes (half the force clamp, in mN), then both modes
amp_max = ((app.ctrl.ulim >> 1) * 1000) >> app.table[app.off['FMT'] + 4]
r1 = app.cmd_excite(1, amp_max, 1)

def phase(mode, n):
    for k in range(n):
        hal.adc = 2048 + ((k * 7) % 41) - 20
        hal.enc = (65530 + k) & 0xFFFF
        app.step()
        app.fill_telemetry(tel)

d1 = alloc_bytes(lambda: phase(1, 1500))
st1 = app.sup.state
r2 = app.cmd_excite(2, amp_max, 3)
d2 = alloc_bytes(lambda: phase(2, 300))

def big(n):
    x = 0
    for k in range(n):
        x = (1 << 30) + k
    return x

dc = alloc_bytes(lambda: big(200))
print(r1, r2, st1, d1, d2, dc)
"""


@pytest.mark.wasm  # skipped without the WebAssembly port (tests/conftest.py)
def test_excitation_allocates_nothing_32bit_wasm() -> None:
    from host.boards.mpyrun import run_wasm

    r1, r2, st1, d1, d2, dc = (int(v) for v in run_wasm(WASM_SCRIPT, timeout=300).split()[-6:])
    assert r1 == T.OK and r2 == T.OK and st1 == 2
    assert dc > 1000  # 2**30 + k is a heap int on this port: the measurement sees it
    assert d1 == 0 and d2 == 0, (d1, d2)


# ---------------------------------------------------------------- upright board excite (issue 22)
# against the virtual board (firmware under the unix port, real time) through the relay of
# tests/test_board_cli.py, whose hands set the sensors

def _relay():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_board_cli import Relay

    return Relay()


@pytest.fixture
def relay():
    r = _relay()
    try:
        yield r
    finally:
        r.close()


def _excite(relay, *argv: str):
    import subprocess

    from test_board_cli import ROOT, UPRIGHT

    return subprocess.Popen([*UPRIGHT, "board", "--port", relay.port, "excite", *argv], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
def test_excite_board_seconds_counts_the_boards_ticks(relay, tmp_path) -> None:
    # --board-seconds: the excitation lasts that many of the board's ticks (one row each at telem_div 1)
    import csv

    out = tmp_path / "cart.csv"
    p = _excite(relay, "--cart-only", "--board-seconds", "1.2", "--board-coast", "0.6", "--amplitude", "0.5",
                "--out", str(out), "--quiet")
    _, err = p.communicate(timeout=90)
    assert p.returncode == 0, err
    rows = list(csv.DictReader(out.open()))
    ex = [r for r in rows if r["excite"] == "2"]
    driven = ex[:max(i for i, r in enumerate(ex) if int(r["duty"]) != 0) + 1]  # up to the disarm
    # 600 ticks excited (+ the ticks of one 20 ms poll), 300 coasting (the rows after the disarm)
    assert 600 <= len(driven) <= 640, len(driven)
    assert 300 <= len(ex) - len(driven) <= 360, len(ex) - len(driven)
    last = err.strip().splitlines()[-1]
    assert "s of board time excited" in last and "coasting" in last, last
    # nothing moves on the relay's frozen sensors: still warned, in one line
    assert sum("nothing moved" in ln for ln in err.splitlines()) == 1, err


@pytest.mark.slow
def test_excite_exits_nonzero_when_the_board_faults(relay, tmp_path) -> None:
    # the pendulum "falls" during a balancing run (the hands tilt it 0.6 rad): the tilt fault ends the run,
    # and the command says so in one line and exits 1 -- the rows received stay on disk
    import csv
    import time

    out = tmp_path / "bal.csv"
    p = _excite(relay, "--board-seconds", "30", "--amplitude", "0.3", "--out", str(out), "--quiet")
    try:
        deadline = time.monotonic() + 60
        # 300 rows of the excitation on disk (the columns excite, exc_amp_n, exc_div end a row)
        while time.monotonic() < deadline and (not out.exists() or
                                               sum(ln.endswith(",1,0.3,4\n") for ln in out.open()) < 300):
            time.sleep(0.2)
        for _ in range(5):
            relay.sensors(2048 + 520, 0)  # +0.6 rad on a 270-degree, 12-bit pot
            time.sleep(0.05)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    lines = err.strip().splitlines()
    assert p.returncode == 1, err
    assert "faulted during the excitation (tilt" in lines[-1] and "kept" in lines[-1], lines[-1]
    assert not any("Traceback" in ln for ln in lines), err
    rows = list(csv.DictReader(out.open()))
    assert sum(r["excite"] == "1" for r in rows) >= 300
