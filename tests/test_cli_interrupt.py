"""Ctrl-C in the long commands (issue 11 item 4): a real ``upright`` process gets SIGINT once
it has started working; it exits 130 without a traceback, writes what finished (marked
partial) and leaves no child process (the MicroPython board) behind."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import psutil
import pytest

ROOT = Path(__file__).resolve().parent.parent


class Cmd:
    """``python -m host.cli.main ARGS`` in its own process group, output to files."""

    def __init__(self, tmp: Path, *args: str) -> None:
        self.out, self.err = tmp / "stdout.txt", tmp / "stderr.txt"
        self.proc = subprocess.Popen([sys.executable, "-m", "host.cli.main", *args], cwd=ROOT,
                                     stdout=self.out.open("w"), stderr=self.err.open("w"), start_new_session=True)
        self.children: list[psutil.Process] = []

    def wait_for(self, cond: Callable[[], bool], what: str, timeout: float = 180.0) -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            assert self.proc.poll() is None, f"ended before {what}: {self.err.read_text()}"
            assert time.monotonic() < deadline, f"no {what} within {timeout} s: {self.err.read_text()}"
            time.sleep(0.05)
        self.children = psutil.Process(self.proc.pid).children(recursive=True)

    def interrupt(self, group: bool = True, timeout: float = 60.0) -> tuple[int, str, str]:
        if group:  # what a terminal's Ctrl-C does: the whole foreground group gets SIGINT
            os.killpg(self.proc.pid, signal.SIGINT)
        else:
            os.kill(self.proc.pid, signal.SIGINT)
        try:
            rc = self.proc.wait(timeout)
        finally:
            if self.proc.poll() is None:
                os.killpg(self.proc.pid, signal.SIGKILL)
        return rc, self.out.read_text(), self.err.read_text()

    def assert_children_gone(self) -> None:
        alive = []
        for c in self.children:
            try:
                if c.is_running() and c.status() != psutil.STATUS_ZOMBIE:
                    alive.append(c)
            except psutil.NoSuchProcess:
                pass
        assert not alive, f"child processes left behind: {[c.cmdline() for c in alive]}"


def _interrupted_cleanly(rc: int, err: str) -> None:
    assert rc == 130, err
    assert "Traceback" not in err, err
    assert "interrupted" in err.splitlines()[-1], err


@pytest.mark.slow
def test_sweep_interrupted_writes_the_finished_runs(tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    cmd = Cmd(tmp_path, "sweep", "robustness", "--n", "100000", "--chunk", "50", "--duration", "1.0",
              "--no-plots", "--out", str(out))
    cmd.wait_for(lambda: re.search(r" [1-9]\d*/100000 runs", cmd.err.read_text()) is not None, "finished runs")
    rc, _, err = cmd.interrupt(group=False)
    _interrupted_cleanly(rc, err)
    assert "partial results" in err
    summary = json.loads((out / "robustness_summary.json").read_text())
    assert summary["partial"] is True and summary["runs_planned"] == 100000
    assert 0 < summary["runs_done"] < 100000 and summary["runs_done"] % 50 == 0
    import pyarrow.parquet as pq

    rows = (out / "robustness.csv").read_text().strip().splitlines()
    assert len(rows) == summary["runs_done"] + 1
    assert pq.read_table(out / "robustness.parquet").num_rows == summary["runs_done"]
    cmd.assert_children_gone()


@pytest.mark.slow
@pytest.mark.parametrize("group", [True, False], ids=["ctrl-c-to-group", "sigint-to-upright"])
def test_hil_interrupted_keeps_finished_scenarios_and_ends_the_board(tmp_path: Path, group: bool) -> None:
    out = tmp_path / "hil"
    cmd = Cmd(tmp_path, "hil", "--virtual", "--scenario", "tilt_0p1,ref_step_20cm,square_wave_20cm_2p2s",
              "--no-plots", "--out", str(out))
    # the second scenario's progress: the first has finished and its files are written
    cmd.wait_for(lambda: "ref_step_20cm:" in cmd.err.read_text(), "the second scenario")
    assert any("micropython" in " ".join(c.cmdline()) for c in cmd.children), cmd.children
    rc, stdout, err = cmd.interrupt(group=group)
    _interrupted_cleanly(rc, err)
    summary = (out / "summary.txt").read_text()
    assert summary.startswith("PARTIAL: interrupted after") and "tilt_0p1" in summary
    assert "square_wave_20cm_2p2s" in summary.splitlines()[0]  # listed as not finished
    assert (out / "tilt_0p1.csv").stat().st_size > 0
    assert "tilt_0p1" in stdout  # the finished runs' table
    cmd.assert_children_gone()


@pytest.mark.slow
def test_demo_interrupted_writes_index_and_partial_summary(tmp_path: Path) -> None:
    cmd = Cmd(tmp_path, "demo", "--out", str(tmp_path), "--no-design", "--no-gif")
    demo = tmp_path / "demo"
    cmd.wait_for(lambda: len(re.findall(r"^  \S+: 0%", cmd.err.read_text(), re.M)) >= 2, "the second scenario")
    rc, _, err = cmd.interrupt()
    _interrupted_cleanly(rc, err)
    assert (demo / "summary.txt").read_text().startswith("PARTIAL")
    assert (demo / "index.html").exists()
    cmd.assert_children_gone()


@pytest.mark.slow
def test_soak_interrupted_prints_the_finished_chunks(tmp_path: Path) -> None:
    cmd = Cmd(tmp_path, "soak", "--sim-seconds", "880", "--chunk", "8.8")
    cmd.wait_for(lambda: re.search(r"^\s+[1-9][\d.]* / 880 s simulated", cmd.err.read_text(), re.M) is not None,
                 "a finished chunk")
    rc, out, err = cmd.interrupt()
    _interrupted_cleanly(rc, err)
    assert "soak: PARTIAL: interrupted after" in out and "no verdict" in out
    assert "chunk" in out  # the finished chunks' table
    cmd.assert_children_gone()


@pytest.mark.slow
@pytest.mark.parametrize("sig,status", [(signal.SIGTERM, 143), (signal.SIGHUP, 129)], ids=["SIGTERM", "SIGHUP"])
def test_hil_terminated_is_handled_as_ctrl_c(tmp_path: Path, sig: int, status: int) -> None:
    """SIGTERM (kill) and SIGHUP (a closed terminal) end a run as Ctrl-C does -- the finished
    scenarios written, the summary marked partial, the board process ended -- with 128 + signal."""
    out = tmp_path / "hil"
    cmd = Cmd(tmp_path, "hil", "--virtual", "--scenario", "tilt_0p1,ref_step_20cm,square_wave_20cm_2p2s",
              "--no-plots", "--out", str(out))
    cmd.wait_for(lambda: "ref_step_20cm:" in cmd.err.read_text(), "the second scenario")
    os.kill(cmd.proc.pid, sig)
    rc = cmd.proc.wait(60)
    err = cmd.err.read_text()
    assert rc == status, err
    assert "Traceback" not in err and f"interrupted by {signal.Signals(sig).name}" in err.splitlines()[-1], err
    assert (out / "summary.txt").read_text().startswith("PARTIAL: interrupted after")
    cmd.assert_children_gone()
