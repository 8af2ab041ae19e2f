"""``upright dashboard --emulate rp2040``: the dashboard server against the board firmware on the
emulated Pico (issue 14: "all of the above runs in make test against the emulated and the virtual
board").

The browser test (tests/test_dashboard_browser.py) drives the page against the virtual board,
whose simulated pendulum moves.  Here the same server runs against MicroPython's rp2 port on the
emulated RP2040 (``upright emulate rp2040 --pty`` started by the dashboard itself; the pendulum is
held upright there and the board runs at ~0.15-0.2x real time), and this test plays the page over
HTTP exactly as ``static/app.js`` does: it opens the event stream (which makes it a page with an
id), pings, arms, sees the board's own heartbeat answer armed/balancing, records, disarms,
downloads the recording, arms again and drops the stream: the server must stop feeding the board
and disarm it by itself.  Every command carries the run's token (from the address the dashboard
prints); one without it is refused.  Last, armed from a new page, SIGTERM ends the dashboard: it
disarms the board first (its own heartbeat says disarmed) and exits with 143.
"""

from __future__ import annotations

import csv
import io
import os
import json
import re
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

import tool_helpers as TH
from host.boards.rp2040.board import ROOT
from host.dashboard.hub import COLUMNS
from host.dashboard.server import PAGE_HEADER, TOKEN_HEADER, split_url

pytestmark = pytest.mark.rp2040  # slow; skipped without the emulated board (tests/conftest.py)


TOKEN = {"": ""}  # this run's token (set from the printed address)


def _req(url: str, data: bytes | None = None, page: str | None = None, token: bool = True) -> tuple[int, dict]:
    headers = {"Content-Type": "application/json"}
    if page is not None:
        headers[PAGE_HEADER] = page
    if token:
        headers[TOKEN_HEADER] = TOKEN[""]
    return TH.http_json(url, data, headers, timeout=30)


class _Page:
    """An open event stream (what makes a page live) read on a thread, and its pings."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.res = urllib.request.urlopen(url + "events", timeout=30)
        first = b""
        while b"\n\n" not in first:
            first += self.res.read1(4096)
        head, _, rest = first.partition(b"\n\n")
        lines = dict(ln.split(": ", 1) for ln in head.decode().splitlines() if ": " in ln)
        assert lines["event"] == "hello"
        self.hello = json.loads(lines["data"])
        self.id = self.hello["id"]
        self.rows = rest.count(b"event: t\n")
        self.stop = threading.Event()
        self.t = threading.Thread(target=self._run, daemon=True)
        self.t.start()
        # app.js pings on its own timer, every 250 ms, whether or not the stream brings rows (a
        # ping sent only after a read stopped with the stream: on a loaded machine -- the suite on
        # two workers -- a stall of the stream over PAGE_TIMEOUT_S made the page dead, the hub
        # stopped feeding and the board latched `watchdog` before the server's disarm reached it)
        self.p = threading.Thread(target=self._ping, daemon=True)
        self.p.start()

    def _run(self) -> None:
        try:
            while not self.stop.is_set():
                chunk = self.res.read1(65536)
                if not chunk:
                    return
                self.rows += chunk.count(b"event: t\n")
        except (OSError, ValueError):
            return

    def _ping(self) -> None:
        while not self.stop.wait(0.25):
            try:
                _req(self.url + "api/ping", b"{}", self.id)
            except OSError:
                return

    def close(self) -> None:
        self.stop.set()
        self.res.close()


def _wait(url: str, pred, seconds: float, what: str) -> dict:
    t0 = time.monotonic()
    while True:
        st = _req(url + "api/status")[1]
        if pred(st):
            return st
        if time.monotonic() - t0 > seconds:
            raise AssertionError(f"waited {seconds} s for {what}: {st.get('heartbeat')}")
        time.sleep(0.2)


def test_dashboard_serves_the_emulated_board(tmp_path: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "host.cli.main", "dashboard", "--emulate", "rp2040",
                             "--http-port", "0", "--record-dir", str(tmp_path)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "UPRIGHT_XIP_CACHE": "0"})  # nothing timed: ideal cycles, faster
    page = None
    try:
        url = proc.stdout.readline().strip()  # type: ignore[union-attr]
        assert url.startswith("http://127.0.0.1:"), (url, proc.stderr.read() if proc.poll() is not None else "")  # type: ignore[union-attr]
        url, TOKEN[""] = split_url(url)
        st = _wait(url, lambda s: s.get("heartbeat") and s.get("telemetry_rows", 0) > 5, 120, "heartbeat and telemetry")
        assert st["heartbeat"]["state_name"] == "disarmed"
        # a command from something that is not a live page is refused; a live page may arm
        code, body = _req(url + "api/arm", b"{}", "cli")
        assert code == 403 and "live dashboard page" in body["error"]
        page = _Page(url)
        _req(url + "api/ping", b"{}", page.id)
        code, body = _req(url + "api/arm", b"{}", page.id, token=False)
        assert code == 403 and TOKEN_HEADER in body["error"]  # a live page's id without the token
        assert _req(url + "api/record/start", b"{}", page.id)[0] == 200
        code, body = _req(url + "api/arm", b"{}", page.id)
        assert code == 200, body
        # the board's own heartbeat says armed or balancing (the pendulum is held upright), and stays
        # so for 3 s of wall time (> 2 s of the board's 250 ms link watchdog at the emulator's speed)
        # because the server feeds it while the page lives
        _wait(url, lambda s: s["heartbeat"]["state_name"] in ("armed", "balancing"), 60, "armed")
        t0 = time.monotonic()
        while time.monotonic() - t0 < 3.0:
            st = _req(url + "api/status")[1]
            assert st["heartbeat"]["state_name"] in ("armed", "balancing"), st["heartbeat"]
            time.sleep(0.25)
        code, body = _req(url + "api/disarm", b"{}", page.id)
        assert code == 200, body
        st = _wait(url, lambda s: s["heartbeat"]["state_name"] == "disarmed", 60, "disarmed")
        # a telemetry row after that heartbeat, so the recording ends with the disarmed state
        _wait(url, lambda s, n=st["telemetry_rows"]: s["telemetry_rows"] > n + 1, 30, "telemetry after the disarm")
        code, rec = _req(url + "api/record/stop", b"{}", page.id)
        assert code == 200 and rec["rows"] > 10 and rec["lost"] == 0, rec
        data = urllib.request.urlopen(url + "api/record.csv", timeout=30).read().decode()
        rows = list(csv.reader(io.StringIO(data)))
        assert tuple(rows[0]) == COLUMNS and len(rows) - 1 == rec["rows"]
        states = [int(float(r[COLUMNS.index("state")])) for r in rows[1:]]
        assert {1, 2} & set(states) and states[-1] == 0  # armed during the recording, disarmed at its end
        assert page.rows > 10  # the stream carried telemetry rows to the page
        # armed again, the page goes away without a disarm: the server stops feeding and disarms
        assert _req(url + "api/arm", b"{}", page.id)[0] == 200
        _wait(url, lambda s: s["heartbeat"]["state_name"] in ("armed", "balancing"), 60, "armed again")
        page.close()
        page = None
        _wait(url, lambda s: s["heartbeat"]["state_name"] == "disarmed" and s["heartbeat"]["faults"] == 0, 60,
              "the server's own disarm after the page closed")
        # armed from a new page, the dashboard is ended by SIGTERM: it disarms first
        page = _Page(url)
        _req(url + "api/ping", b"{}", page.id)
        assert _req(url + "api/arm", b"{}", page.id)[0] == 200
        _wait(url, lambda s: s["heartbeat"]["state_name"] in ("armed", "balancing"), 60, "armed for SIGTERM")
        proc.send_signal(signal.SIGTERM)
        out = proc.communicate(timeout=60)
        assert proc.returncode == 128 + signal.SIGTERM, out[1][-2000:]
        assert re.search(r"board disarmed in \d+ ms \(its heartbeat: disarmed\)", out[1]), out[1][-2000:]
    finally:
        if page is not None:
            page.close()
        if proc.returncode is None:  # a step above failed: end it as Ctrl-C does
            proc.send_signal(2)
            try:
                out = proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                out = proc.communicate()
            assert proc.returncode in (0, 130), out[1][-2000:]
