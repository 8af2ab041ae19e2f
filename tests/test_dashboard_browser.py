"""``upright dashboard --virtual`` in a real browser (issue 14 item 4).

Headless Chromium (Debian's ``chromium``, installed by ``make setup``) driven by playwright-core
(``node_modules``, pinned in package.json) through ``host/dashboard/e2e.mjs``: the page loads
against the virtual board (the firmware under MicroPython on a pty, balancing the simulated
robot), shows live data, arms the board (the state on the page, in the server's view of the
link and in the firmware's own loop answers), steps the reference and sees the cart follow,
disarms, downloads a recording whose rows are the telemetry rows the page received, and, armed
again, is closed without a disarm: the server must stop the host heartbeat and disarm.

The page sends this run's token with every command (a fetch from the page without it is refused
with 403), and the force plot shows the applied force: 0 on every point drawn while the board is
not balancing, whatever force value the telemetry still carries after a disarm.

Measured here and asserted: at least 20 screen updates per second, and frame-to-screen latency
(the server's receive time of a telemetry frame to the animation frame after the one that drew
it) under 100 ms at the 95th percentile.

Skipped only where Chromium is genuinely absent and not in CI (``CI`` set: a failure).
``UPRIGHT_DASHBOARD_SCREENSHOT=PATH`` saves the page in motion there
(``make dashboard-screenshot`` writes ``docs/img/dashboard.png``).
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from host.dashboard.hub import COLUMNS

ROOT = Path(__file__).resolve().parent.parent
CHROMIUM = os.environ.get("CHROMIUM", "/usr/bin/chromium")
E2E = ROOT / "host" / "dashboard" / "e2e.mjs"


def _need_browser() -> None:
    missing = []
    if not Path(CHROMIUM).exists():
        missing.append(f"{CHROMIUM} (Debian package chromium: make setup installs it)")
    if shutil.which("node") is None:
        missing.append("node")
    if not (ROOT / "node_modules" / "playwright-core").is_dir():
        missing.append("node_modules/playwright-core (npm ci)")
    if missing:
        why = "browser test needs " + ", ".join(missing)
        if os.environ.get("CI"):
            pytest.fail(why + " -- CI must run it")
        print("SKIPPED:", why, file=sys.stderr)
        pytest.skip(why)


@pytest.fixture
def dashboard(tmp_path: Path):
    proc = subprocess.Popen([sys.executable, "-m", "host.cli.main", "dashboard", "--virtual", "--http-port", "0",
                             "--record-dir", str(tmp_path / "rec")],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = proc.stdout.readline().strip()  # type: ignore[union-attr]
        assert url.startswith("http://127.0.0.1:"), (url, proc.stderr.read() if proc.poll() is not None else "")  # type: ignore[union-attr]
        assert "?token=" in url  # the page's address carries this run's token
        yield url, proc
    finally:
        if proc.poll() is None:
            proc.send_signal(2)  # Ctrl-C: the dashboard disarms and ends the board
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@pytest.mark.slow
def test_dashboard_in_chromium(dashboard, tmp_path: Path) -> None:
    _need_browser()
    url, proc = dashboard
    shot = os.environ.get("UPRIGHT_DASHBOARD_SCREENSHOT") or str(tmp_path / "dashboard.png")
    t0 = time.monotonic()
    r = subprocess.run(["node", str(E2E), url, str(tmp_path / "e2e"), shot], cwd=ROOT, capture_output=True,
                       text=True, timeout=180, env=dict(os.environ, CHROMIUM=CHROMIUM))
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    assert lines, f"e2e printed nothing (status {r.returncode}): {r.stderr[-2000:]}"
    res = json.loads(lines[-1])
    print(json.dumps({k: v for k, v in res.items() if k != "notes"}, indent=1), f"\nbrowser run {time.monotonic() - t0:.1f} s")
    assert res["ok"], res.get("error")
    assert r.returncode == 0

    # live data, arm and disarm seen on the page, in the server's view of the link and in the
    # firmware's own per-tick answers
    # the board's 50 Hz telemetry; on a loaded machine the virtual board falls behind real time
    # (it skips the time, never bursts: `behind_s`) and sends fewer rows per wall-clock second --
    # that every row the server read reached the page is checked on the recording below
    assert res["rows_per_s_page"] >= (40 if res["behind_s"] == 0 else 20), res
    assert res["armed_page"] in ("armed", "balancing") and res["armed_link"] in ("armed", "balancing")
    assert res["armed_fw_state"] in (1, 2)
    assert res["feeding_armed"] is True and res["feeding_disarmed"] is False
    assert res["disarmed_page"] == "disarmed" and res["disarmed_link"] == "disarmed"
    # commands only with the token; the force plot: the telemetry's force while balancing, 0 otherwise
    assert res["no_token_status"] == 403 and "token" in res["no_token_error"]
    fd = res["force_drawn"]
    assert fd["balancing_points"] > 100 and fd["idle_points"] > 20, fd
    assert fd["balancing_drawn_equal"] and fd["idle_drawn_nonzero"] == 0, fd
    # the firmware balances the simulated robot through the step (it tilts, it does not fall)
    assert 0.001 < res["tilt_max_after_step"] < 0.3

    # the figures: >= 20 updates per second, < 100 ms from telemetry frame to screen
    page = res["page"]
    assert page["updates_per_s"] >= 20, page
    assert page["latency_ms"]["n"] >= 100, page
    assert page["latency_ms"]["p95"] < 100, page

    # the page closed while armed: heartbeat stopped and the board disarmed, well within a second or two
    assert res["after_close"] == "disarmed"
    assert res["disarmed_after_close_ms"] < 2500
    assert any("last page closed" in n for n in res["notes"])

    # the downloaded recording: every row one telemetry frame, none lost, identical to what
    # the page received
    with open(res["csv"], newline="") as fh:
        rows = list(csv.reader(fh))
    assert tuple(rows[0]) == COLUMNS
    assert res["record"]["lost"] == 0 and res["record"]["rows"] == len(rows) - 1  # by the board's sequence numbers
    body = [[float(v) for v in row] for row in rows[1:]]
    assert len(body) > 200  # ~8 s at 50 Hz
    ns = [int(r[0]) for r in body]
    assert ns == list(range(ns[0], ns[0] + len(ns))), "rows missing from the recording"
    page_rows = json.loads((tmp_path / "e2e" / "page_rows.json").read_text())
    seen = {int(r[0]): [float(v) for v in r] for r in page_rows["rows"]}
    assert page_rows["columns"] == list(COLUMNS)
    common = [r for r in body if int(r[0]) in seen]
    assert len(common) == len(body), f"{len(body) - len(common)} recorded rows never reached the page"
    for r in common:
        assert r == seen[int(r[0])], f"row {int(r[0])}: recording {r} != page {seen[int(r[0])]}"
    states = [int(r[COLUMNS.index("state")]) for r in body]
    assert 2 in states and states[-1] == 0  # balancing during the recording, disarmed at its end
    x = [r[COLUMNS.index("x")] for r in body]
    assert max(x) > 0.1  # the cart followed the step and the square wave

    assert Path(shot).stat().st_size > 20000
