"""``upright commission`` stage by stage, and the board tools' waits scaled by the board's clock.

The whole ``commission --port`` on the virtual robot (the emulated Pico over its pty) is run by
tests/test_readme_robot.py::test_9_commission_stage_by_stage, as the README shows it; here:
the scaling helper (:mod:`host.hil.answer_time`) used by every board tool, a board at full speed
keeping the full-speed request time (the unix-port virtual board in real time), and ``--until`` /
``--resume`` one stage per command (lockstep HIL on the unix port: seconds, not minutes).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from host.hil import answer_time as AT

ROOT = Path(__file__).resolve().parent.parent
UPRIGHT = [sys.executable, "-m", "host.cli.main"]


def test_request_time_and_waits_scale_with_the_board_clock() -> None:
    # full speed: the tools' 0.3 s; the emulated board at 0.15x: 2 s; never past REQUEST_MAX_S
    assert AT.request_time(1.0) == pytest.approx(AT.REQUEST_S)
    assert AT.request_time(0.15) == pytest.approx(AT.REQUEST_S / 0.15)
    assert AT.request_time(0.001) == AT.REQUEST_MAX_S
    assert AT.request_time(2.0) == pytest.approx(AT.REQUEST_S)  # a board is not faster than real time
    assert AT.request_time(0.01, base=20.0) == 20.0  # a longer base is never cut
    # board seconds -> wall seconds
    assert AT.wall_time(5.0, 1.0) == pytest.approx(5.0)
    assert AT.wall_time(5.0, 0.2) == pytest.approx(25.0)
    assert AT.wall_time(1.0, 0.0) == pytest.approx(1.0 / (AT.BASE_S / AT.MAX_S))


def test_the_host_heartbeat_keeps_to_the_board_clock() -> None:
    # every 25 ms of board time: 50 ms of wall at full speed (the link's HOST_HEARTBEAT_S), 167 ms
    # at 0.15x, never more than KEEPALIVE_MAX_S apart however slow the board
    assert AT.keepalive_period(1.0) == pytest.approx(0.05)
    assert AT.keepalive_period(0.15) == pytest.approx(AT.KEEPALIVE_BOARD_S / 0.15)
    assert AT.keepalive_period(0.001) == AT.KEEPALIVE_MAX_S
    # the board's speed followed from its heartbeats' uptime (16 bits: across the wrap too)
    ck = AT.ClockTrack(window=1.0)
    t, u = 100.0, 65000
    for _ in range(12):  # 0.15x: 100 ms of board time every 0.667 s of wall
        t += 0.6667
        u = (u + 100) % 65536
        sp = ck.observe(u, t)
    assert sp == pytest.approx(0.15, rel=0.01)
    for _ in range(6):  # the board speeds up to 0.5x: followed within the window (1 s of wall)
        t += 0.2
        u = (u + 100) % 65536
        sp = ck.observe(u, t)
    assert sp == pytest.approx(0.5, rel=0.05)
    t += 0.2
    assert ck.observe(10, t) == pytest.approx(0.5, rel=0.05)  # a reset (uptime back to 0): start again


@pytest.mark.slow  # the unix-port virtual board in real time: ~3 s
def test_a_board_at_full_speed_keeps_the_full_speed_request_time() -> None:
    sys.path.insert(0, str(Path(__file__).parent))
    from test_board_cli import Relay

    from host.operate.board import Board

    r = Relay()
    try:
        with Board.open(r.port) as b:
            # measured, not assumed: the real-time board's clock runs with the wall's -- nearly: on this
            # 2-core machine at a load of 13 the unix port's "real time" was seen at 0.68x
            assert 0.3 <= b.speed <= 1.0, b.speed
            assert b.timeout == pytest.approx(AT.REQUEST_S / b.speed) and b.timeout < 1.0
            assert b.wall(2.0) == pytest.approx(2.0 / b.speed)
            assert b.state()["state_name"] == "disarmed"
        with Board.open(r.port, timeout=1.5) as b:  # --timeout fixes it: no measurement
            assert b.timeout == 1.5 and b.speed == 1.0
    finally:
        r.close()


def _commission(*argv: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([*UPRIGHT, "commission", *argv], cwd=cwd, capture_output=True, text=True, timeout=600)


def test_until_refuses_an_unknown_stage_in_one_line(tmp_path: Path) -> None:
    r = _commission("--virtual", "--plant", "soft_pendulum", "--out", "c", "--until", "balancing", cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    line = r.stderr.strip().splitlines()[-1]
    assert "--until" in line and "'balancing'" in line and "identity, sensors, calibrate" in line, r.stderr
    assert not (tmp_path / "c").exists()  # refused before anything ran


@pytest.mark.slow  # lockstep HIL on the unix port, three processes: ~10-20 s
def test_until_stops_after_a_stage_and_resume_goes_on_one_stage_per_command(tmp_path: Path) -> None:
    base = ["--virtual", "--plant", "soft_pendulum", "--out", "c", "--fast"]
    r = _commission(*base, "--until", "sensors", cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "stopped after sensors (--until): done identity, sensors; --resume goes on" in r.stdout, r.stdout
    state = json.loads((tmp_path / "c" / "commission.json").read_text())
    assert state["done"] == ["identity", "sensors"]
    # the same command again refuses (a commissioning is there): --resume
    again = _commission(*base, "--until", "sensors", cwd=tmp_path)
    assert again.returncode == 2 and "--resume" in again.stderr.strip().splitlines()[-1], again.stderr
    r = _commission(*base, "--resume", "--until", "calibrate", cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "[identity]" not in r.stdout and "[sensors]" not in r.stdout and "[calibrate]" in r.stdout, r.stdout
    state = json.loads((tmp_path / "c" / "commission.json").read_text())
    assert state["done"] == ["identity", "sensors", "calibrate"]
    assert (tmp_path / "c" / "robot_cal.toml").exists() and (tmp_path / "c" / "table.bin").exists()
    # a stage already done: nothing to run, still exit 0 and the same state
    r = _commission(*base, "--resume", "--until", "sensors", cwd=tmp_path)
    assert r.returncode == 0 and "[" not in "".join(ln for ln in r.stdout.splitlines() if ln.startswith("[")), r.stdout
    assert json.loads((tmp_path / "c" / "commission.json").read_text())["done"] == state["done"]
