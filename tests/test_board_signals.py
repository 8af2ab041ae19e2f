"""Tools that die disarm, one tool per port (issue 23 item 4, issue 22 item 3).

``upright board arm`` / ``excite`` against the virtual board (firmware under the MicroPython
unix port, real time; :class:`test_board_cli.Relay`): SIGTERM, SIGHUP and a closed terminal
disarm the board as Ctrl-C does before the tool exits (128 + signal).  "Disarmed" is checked
on the board right after the exit: state ``disarmed`` with no fault flag -- the link
watchdog (250 ms without host frames) would have latched ``watchdog`` instead.  A second
tool on the same port is refused in one line naming the process that holds it.
"""

from __future__ import annotations

import fcntl
import json
import os
import select
import signal
import subprocess
import termios
import time

import pytest

import tool_helpers as TH
from test_board_cli import ROOT, UPRIGHT, board, relay  # noqa: F401 - the fixture

pytestmark = pytest.mark.slow


def _wait_line(proc: subprocess.Popen, text: str, timeout: float = 60) -> str:
    deadline = time.monotonic() + timeout
    seen = ""
    while text not in seen and time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line and proc.poll() is not None:
            break
        seen += line
    assert text in seen, seen + (proc.stderr.read() if proc.poll() is not None else "")
    return seen


def _board_state(r) -> dict:
    p = board(r, "status", "--json")
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout)


def _assert_disarmed_by_the_tool(r) -> None:
    st = _board_state(r)
    # a watchdog expiry would read state "fault", faults "watchdog"
    assert st["state"] == "disarmed" and st["faults"] == 0, st


@pytest.mark.parametrize("sig,status", [(signal.SIGTERM, 143), (signal.SIGHUP, 129)], ids=["SIGTERM", "SIGHUP"])
def test_signal_during_arm_disarms(relay, sig, status):  # noqa: F811 - the fixture
    proc = subprocess.Popen([*UPRIGHT, "board", "--port", relay.port, "arm"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen = _wait_line(proc, "armed;")
    time.sleep(0.5)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == status, seen + err
    assert "upright board: disarmed" in err and f"interrupted by {signal.Signals(sig).name}" in err, err
    assert "Traceback" not in err, err
    _assert_disarmed_by_the_tool(relay)


def test_closed_terminal_during_arm_disarms(relay):  # noqa: F811
    """The tool on a terminal (a pty as its controlling tty) that is closed: the kernel's
    SIGHUP, then writes to the gone terminal fail -- the board is disarmed all the same."""
    master, slave = os.openpty()

    def own_terminal() -> None:
        os.setsid()
        fcntl.ioctl(slave, termios.TIOCSCTTY, 0)

    proc = subprocess.Popen([*UPRIGHT, "board", "--port", relay.port, "arm"], cwd=ROOT, stdin=slave,
                            stdout=slave, stderr=slave, preexec_fn=own_terminal)
    os.close(slave)
    out = b""
    deadline = time.monotonic() + 60
    try:
        while b"armed;" not in out and time.monotonic() < deadline and proc.poll() is None:
            if select.select([master], [], [], 0.2)[0]:
                try:
                    out += os.read(master, 4096)
                except OSError:
                    break
        assert b"armed;" in out, out
        time.sleep(0.5)
    finally:
        os.close(master)  # the terminal window closes
    assert proc.wait(timeout=30) == 129, out
    _assert_disarmed_by_the_tool(relay)


def test_sigterm_during_excite_disarms(relay, tmp_path):  # noqa: F811
    out = tmp_path / "bal.csv"
    proc = subprocess.Popen([*UPRIGHT, "board", "--port", relay.port, "excite", "--seconds", "30",
                             "--amplitude", "0.3", "--out", str(out)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen = _wait_line(proc, "rows,")  # the progress bar: armed, balancing, excitation on
    time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 143, seen + err
    assert out.stat().st_size > 0
    _assert_disarmed_by_the_tool(relay)
    p = board(relay, "params", "get", "telem_div", "--json")
    assert json.loads(p.stdout) == {"telem_div": 10}  # put back on the way out


def test_tools_share_one_board_through_the_owners_hub(relay, tmp_path):  # noqa: F811
    """``arm`` holds the port; ``status`` and ``log`` attach to its hub and see the balancing
    board, every telemetry frame accounted for; Ctrl-C on ``arm`` still disarms."""
    proc = subprocess.Popen([*UPRIGHT, "board", "--port", relay.port, "arm"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_line(proc, "armed;")
        p = board(relay, "status", "--json")
        assert p.returncode == 0, p.stderr
        assert f"held by PID {proc.pid} (upright board --port {relay.port} arm): sharing" in p.stderr, p.stderr
        st = json.loads(p.stdout)
        assert st["state"] in ("armed", "balancing") and st["faults"] == 0, st
        out = tmp_path / "shared.csv"
        p = board(relay, "log", "--seconds", "2", "--out", str(out))
        assert p.returncode == 0, p.stderr
        n, frames, last = TH.log_summary(p.stderr)
        assert last.endswith("0 lost"), last
        # every tick's pair through the hub (the rate itself, 50 rows/s of a board in real time
        # on a loaded machine, is test_board_cli's business)
        assert n == frames // 2 and n > 20, last
        assert proc.poll() is None, proc.stderr.read()  # the owner is undisturbed
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    assert "upright board: disarmed" in err, err
    _assert_disarmed_by_the_tool(relay)


def test_a_port_held_by_another_program_is_refused_naming_it(relay):  # noqa: F811
    import serial

    held = serial.Serial(relay.port, 115200, timeout=0, exclusive=True)  # as mpremote or a terminal would
    try:
        p = board(relay, "status")
    finally:
        held.close()
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 1 and len(lines) == 1, p.stderr
    assert "port busy" in lines[0] and f"PID {os.getpid()}" in lines[0], lines


def test_sigterm_during_calibrates_motor_step_disarms(relay, tmp_path):  # noqa: F811
    """Step 4 of ``calibrate`` arms the board (wheels lifted, low max_duty): SIGTERM there
    disarms it and puts max_duty back, as Ctrl-C does."""
    out = tmp_path / "robot.toml"
    before = json.loads(board(relay, "params", "get", "max_duty", "--json").stdout)
    proc = subprocess.Popen([*UPRIGHT, "board", "--port", relay.port, "calibrate", "--out", str(out)], cwd=ROOT,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # the user's hands, as in test_board_cli.test_calibrate_scripted
    hands = {**TH.CALIBRATE_HANDS, "Step 4/4: WHEELS": (2100, 363)}
    lines: list[str] = []
    try:
        lines, tilt = TH.answer_prompts(proc, relay, hands, until="Step 4/4: tilt")
        if tilt:
            time.sleep(0.3)  # armed, the host heartbeat running
            proc.send_signal(signal.SIGTERM)
        rest, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, "".join(lines) + err
    _assert_disarmed_by_the_tool(relay)
    assert json.loads(board(relay, "params", "get", "max_duty", "--json").stdout) == before


def test_a_tool_outlives_the_owner_of_the_port(relay, tmp_path):  # noqa: F811
    """``status --watch`` holds the port, ``arm`` attaches to its hub; the watch is stopped
    first: ``arm`` takes the port over and keeps the host heartbeat going -- no watchdog
    fault, a clean disarm at the end of its --seconds."""
    from host.link.porthub import port_holders

    owner = subprocess.Popen([*UPRIGHT, "board", "--port", relay.port, "status", "--watch"], cwd=ROOT,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not any(pid == owner.pid for pid, _ in port_holders(relay.port)):
        assert time.monotonic() < deadline and owner.poll() is None, owner.stderr.read()
        time.sleep(0.1)
    arm = subprocess.Popen([*UPRIGHT, "board", "--port", relay.port, "arm", "--seconds", "4"], cwd=ROOT,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen = _wait_line(arm, "armed;")
    assert "sharing the board through its hub" in seen, seen  # it did attach to the watch's hub
    owner.send_signal(signal.SIGINT)
    _, oerr = owner.communicate(timeout=60)
    assert owner.returncode == 130, oerr
    _, err = arm.communicate(timeout=60)
    assert arm.returncode == 0, seen + err
    lines = [ln for ln in (seen + err).splitlines() if ln.startswith("upright board: ")]
    assert lines[-1] == "upright board: disarmed", lines  # not a fault: the heartbeat never stopped
    _assert_disarmed_by_the_tool(relay)
