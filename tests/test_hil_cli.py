"""`upright hil` and `upright demo` end to end (virtual board), and their one-line errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

import host.hil.runs
from host.cli.main import main
from host.boards.mpyrun import ROOT
from sim.scenario import scenario_from_dict


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "host.cli.main", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)


@pytest.mark.slow
def test_hil_cli_runs_a_scenario_and_writes_outputs(tmp_path: Path) -> None:
    r = _cli("hil", "--virtual", "--scenario", "tilt_0p1", "--no-gif", "--out", str(tmp_path))
    assert r.returncode == 0, r.stdout + r.stderr
    assert "tilt_0p1" in r.stdout and "PASS" in r.stdout and "|dphi| vs float" in r.stdout
    assert "100%" in r.stderr  # progress
    assert (tmp_path / "tilt_0p1.csv").stat().st_size > 0
    assert (tmp_path / "tilt_0p1.png").stat().st_size > 0


@pytest.mark.slow
def test_hil_cli_exits_0_when_the_verdicts_match_a_falling_scenario(tmp_path: Path) -> None:
    # tilt_0p3 starts at 0.3 rad, so |phi| < 0.3 is expected to FAIL (documented); the
    # firmware's catch mode recovers it, the float reference (tracking row only) falls and
    # is compared only up to the catch switch, so the run is as expected: exit 0 (about 5 s)
    r = _cli("hil", "--virtual", "--scenario", "tilt_0p3", "--no-plots", "--quiet", "--out", str(tmp_path))
    assert r.returncode == 0, r.stdout + r.stderr
    assert "FAIL*" in r.stdout and "0 unexpected outcome(s)" in r.stdout and "not as expected" not in r.stdout


@pytest.mark.slow
@pytest.mark.parametrize("args, needle", [
    (("--port", "/dev/does-not-exist-upright"), "/dev/does-not-exist-upright"),
    (("--port", "/dev/does-not-exist-upright", "--link", "can", "--can-interface", "serial"), "CAN channel"),
    (("--port", "can9", "--link", "can", "--can-interface", "no-such-interface"), "not a python-can interface"),
    (("--scenario", "no_such_scenario"), "no_such_scenario"),
])
def test_hil_cli_bad_port_or_scenario_is_one_line(args, needle, tmp_path: Path) -> None:
    r = _cli("hil", *args, "--out", str(tmp_path), "--quiet")
    assert r.returncode != 0
    err = r.stderr.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert needle in err


def test_demo_runs_and_writes_an_index(tmp_path: Path, monkeypatch, capsys) -> None:
    short = scenario_from_dict({"name": "demo_short", "description": "a short tilt", "duration": 1.0,
                                "initial": {"phi": 0.05}, "expect": {"a_max": "any"}})
    monkeypatch.setattr(host.hil.runs, "resolve_scenarios", lambda spec: [short])
    assert main(["demo", "--out", str(tmp_path), "--no-design", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "demo_short" in out and "index.html" in out
    page = (tmp_path / "demo" / "index.html").read_text()
    assert "demo_short.gif" in page and "demo_short.png" in page


def test_hil_port_that_never_answers_is_one_line_naming_the_wait(tmp_path: Path) -> None:
    # a real pty with nothing behind it (the test holds the other end): the first answer is
    # waited for --answer-timeout seconds, then one line naming the port and the flag
    import os
    import pty

    master, slave = pty.openpty()
    try:
        name = os.ttyname(slave)
        r = _cli("hil", "--port", name, "--answer-timeout", "0.5", "--scenario", "tilt_0p1", "--out", str(tmp_path),
                 "--quiet")
    finally:
        os.close(master)
        os.close(slave)
    assert r.returncode == 1, r.stderr
    err = r.stderr.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert f"no answer from {name} within 0.5 s (--answer-timeout)" in err, err


@pytest.mark.parametrize("flag", ["--timeout", "--answer-timeout"])
def test_hil_answer_times_refuse_nonsense(flag: str, tmp_path: Path) -> None:
    r = _cli("hil", "--virtual", flag, "0", "--out", str(tmp_path))
    assert r.returncode == 2 and flag in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_the_answer_time_follows_the_boards_speed() -> None:
    from host.hil.answer_time import BASE_S, MAX_S, answer_time

    assert answer_time(1.0) == BASE_S and answer_time(3.0) == BASE_S  # a board at full speed: 2 s
    assert answer_time(0.1) == pytest.approx(10 * BASE_S)  # the emulated Pico at 0.1x: 20 s
    assert answer_time(0.0) == MAX_S and answer_time(1e-6) == MAX_S  # a clock that stands still: bounded
