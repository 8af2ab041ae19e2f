"""``make flash`` says what it waits for and gives up in seconds (issue 22 item 3):
:mod:`host.boards.flash` against a port that does not exist, a silent pty, the upright link
(the virtual board) and a real MicroPython REPL (the unix port's, on a pty)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from host.boards import flash as F
from host.boards.vport import PTMX, slave_of
from proto_helpers import PtyBridge

ROOT = Path(__file__).resolve().parent.parent
MICROPYTHON = Path(sys.executable).parent / "micropython"


def _flash(*argv: str, timeout: float = 60) -> tuple[int, str, float]:
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "host.boards.flash", *argv], cwd=ROOT, capture_output=True, text=True,
                       timeout=timeout, env={**os.environ, "PYTHONPATH": str(ROOT)})
    return p.returncode, p.stderr.strip(), time.monotonic() - t0


def test_no_such_port(tmp_path) -> None:
    rc, err, _ = _flash("--port", "/dev/upright-no-such-port", "--bundle", str(ROOT / "firmware"))
    assert rc == 1 and "no such port" in err.splitlines()[-1], err


def test_silent_port_gives_up_in_seconds_saying_what_it_waited_for() -> None:
    fd = os.open(PTMX, os.O_RDWR | os.O_NOCTTY)
    try:
        rc, err, took = _flash("--port", slave_of(fd), "--bundle", str(ROOT / "firmware"), "--timeout", "1")
    finally:
        os.close(fd)
    lines = err.splitlines()
    assert rc == 1, err
    assert "waiting up to 1 s for MicroPython's REPL" in lines[0], err
    assert "no MicroPython REPL" in lines[-1] and "within 1 s" in lines[-1] and "nothing" in lines[-1], err
    assert took < 30  # mpremote alone: minutes


@pytest.mark.slow
def test_the_upright_link_is_named_with_what_to_do() -> None:
    from host.boards.vport import VirtualBoard

    cable = PtyBridge()  # a process on its end a, the tool on b
    board = VirtualBoard(cable.a, mode="realtime").start()
    try:
        with pytest.raises(F.FlashError, match="answers with the upright link's frames") as exc:
            F.probe_repl(cable.b, timeout=3.0)
        assert "mode repl" in str(exc.value)
    finally:
        board.stop()
        cable.close()


@pytest.mark.slow
def test_a_real_repl_is_found_and_mpremote_gets_a_time_limit(tmp_path) -> None:
    cable = PtyBridge()  # a process on its end a, the tool on b
    tty = os.open(cable.a, os.O_RDWR)
    repl = subprocess.Popen([str(MICROPYTHON)], stdin=tty, stdout=tty, stderr=tty, start_new_session=True)
    os.close(tty)
    try:
        assert F.probe_repl(cable.b, timeout=10.0) == "repl"
        # an mpremote that never returns: flash gives up after its copy time limit
        stuck = tmp_path / "mpremote"
        stuck.write_text("#!/bin/sh\nsleep 60\n")
        stuck.chmod(0o755)
        t0 = time.monotonic()
        with pytest.raises(F.FlashError, match="did not finish within 1 s"):
            F.flash(cable.b, ROOT / "firmware", mpremote=str(stuck), timeout=10.0, copy_timeout=1.0)
        assert time.monotonic() - t0 < 30
    finally:
        repl.kill()
        repl.wait()
        cable.close()
