"""What the tests of the board tools and the dashboard share: reading a tool's summary line, the
user's hands at ``calibrate``'s prompts, asking the dashboard's HTTP API, and the process tree of an
emulator stopped by Ctrl-C (imported by name: ``import tool_helpers as TH``)."""

from __future__ import annotations

import json
import os
import signal
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any


def log_summary(stderr: str) -> tuple[int, int, str]:
    """``upright board log``'s last summary line ``upright board: N rows (M telemetry frames) ...;
    K lost``: ``(N, M, line)``."""
    line = [s for s in stderr.splitlines() if "rows (" in s][-1]
    return int(line.split("upright board: ")[1].split()[0]), int(line.split("(")[1].split()[0]), line


def logged_rows(proc: Any, out: Path) -> tuple[list[dict[str, str]], str]:
    """A finished ``upright board log --out out.csv``: it exited 0, and the file holds the rows its
    summary line counts, one per TELEM_STATE + TELEM_CTRL pair.  Returns the rows and the summary
    line."""
    import csv

    assert proc.returncode == 0, proc.stderr
    rows = list(csv.DictReader(out.open()))
    n_rows, frames, line = log_summary(proc.stderr)
    assert len(rows) == n_rows == frames // 2
    return rows, line


def http_json(url: str, data: bytes | None = None, headers: dict | None = None,
              timeout: float = 10) -> tuple[int, dict]:
    """GET (or POST ``data``) ``url``: the status and the JSON body, also of an HTTP error."""
    r = urllib.request.Request(url, data=data, headers=headers or {}, method="POST" if data is not None else "GET")
    try:
        with urllib.request.urlopen(r, timeout=timeout) as res:
            return res.status, json.loads(res.read() or b"{}")
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read() or b"{}")


CALIBRATE_HANDS = {"Step 1/4: hold": (2100, 0), "Step 2/4": (2252, 0), "Step 3/4: back upright": (2100, 1000),
                   "Step 3/4: roll": (2100, 1000 - 637)}
"""The user's hands in ``upright board calibrate``: prompt -> (ADC, encoder) the relay's board then
reads: upright at 2100 counts, +10 deg = +152 counts (270-degree pot, 12 bits), the cart rolled
10 cm = -637 counts (encoder reversed)."""


def answer_prompts(proc: Any, relay: Any, hands: dict[str, tuple[int, int]],
                   until: str | None = None) -> tuple[list[str], bool]:
    """Read a tool's output line by line; at each prompt of ``hands`` set the relay's sensors and
    press Enter.  Returns the lines read and whether a line starting with ``until`` came (reading
    stops there) -- else the tool's output ended."""
    lines = []
    while True:
        line = proc.stdout.readline()
        if not line:
            return lines, False
        lines.append(line)
        if until is not None and line.startswith(until):
            return lines, True
        for key, (adc, enc) in hands.items():
            if line.startswith(key):
                for _ in range(3):
                    relay.sensors(adc, enc)
                time.sleep(0.2)
                proc.stdin.write("\n")
                proc.stdin.flush()


def descendants(pid: int) -> set[int]:
    """Every process below ``pid`` (children of all its threads, recursively)."""
    out: set[int] = set()
    todo = [pid]
    while todo:
        p = todo.pop()
        try:
            tids = os.listdir(f"/proc/{p}/task")
        except OSError:
            continue
        for tid in tids:
            try:
                kids = Path(f"/proc/{p}/task/{tid}/children").read_text().split()
            except OSError:
                continue
            for k in map(int, kids):
                if k not in out:
                    out.add(k)
                    todo.append(k)
    return out


def alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def default_sigint() -> None:
    """``preexec_fn`` of an emulator that must see Ctrl-C as a terminal would deliver it (a pytest
    started from a non-interactive shell's background job inherits SIGINT ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def ctrl_c_leaves_nothing(p: Any) -> None:
    """Ctrl-C to the emulator ``p`` (a Popen started in its own session, its node child running):
    it exits 130 saying "interrupted", without a traceback, and leaves no process behind."""
    kids = descendants(p.pid)
    assert kids, "the emulator runs in a child process (node)"
    os.killpg(p.pid, signal.SIGINT)
    _, err = p.communicate(timeout=30)
    assert p.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err, err
    left = [k for k in kids if alive(k)]
    assert not left, f"processes left behind: {left}"
