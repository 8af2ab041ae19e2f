"""``upright dashboard`` without a browser: gain tables, the watchdog policy, the HTTP guards, bad input.

The policy test drives :class:`host.dashboard.hub.Hub` over a scripted link that answers every
command (no board needed): no page, no host heartbeat; a live page's arm starts it; the page
going silent stops it and disarms.  The server test runs ``upright dashboard --virtual`` and
talks to it over HTTP.  The browser test is tests/test_dashboard_browser.py.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from host.dashboard import gains as G
from host.dashboard.hub import PAGE_TIMEOUT_S, Hub, SharedLink
from host.link import messages as M
from host.link.clients import Link
from host.operate.board import has_message

ROOT = Path(__file__).resolve().parent.parent
# the frame that feeds the board's watchdog: the protocol's host heartbeat where it has one
KEEP = "host_heartbeat" if has_message("host_heartbeat") else "request"


# ---------------------------------------------------------------- gain tables
def test_a_gains_module_and_its_blob_give_the_shipped_table(tmp_path: Path) -> None:
    from host.design.export import export, render

    fd = export()
    blob, label = G.design_table("shipped")
    assert blob == fd.blob()
    got, lab = G.table_bytes(render(fd).encode(), "gains.py")
    assert got == blob and "gains.py" in lab and f"{fd.crc():#06x}" in lab
    assert G.table_bytes(blob, "t.bin")[0] == blob
    # the shipped firmware table is this one
    assert (ROOT / "firmware" / "gains.py").read_text().count(f"CRC = const({fd.crc():#06X}".replace("0X", "0x")) == 1


@pytest.mark.parametrize("data, why", [
    (b"", "not a gain table"), (b"abc", "not a gain table"), (b"\x00" * 5000, "not a gain table"),
    (b"FLAT = (1, 'a')\n", "tuple of integers"), (b"FLAT = foo()\n", "literal"),
])
def test_bad_table_files_are_refused(data: bytes, why: str) -> None:
    with pytest.raises(G.TableError, match=why):
        G.table_bytes(data, "x")


def test_unknown_design_is_refused() -> None:
    with pytest.raises(G.TableError, match="shipped"):
        G.design_table("nope")


# ---------------------------------------------------------------- the watchdog policy
class _Board(Link):
    """Answers every board-bound command with an ACK (through the hub, as a pump would)."""

    def __init__(self) -> None:
        super().__init__()
        self.hub: Hub | None = None
        self.log: list[tuple[float, str]] = []
        self.state = 0

    def _send(self, msg: M.Message, seq: int) -> None:
        self.log.append((time.monotonic(), msg.NAME))
        if msg.NAME == "arm":
            self.state = 2
        elif msg.NAME == "disarm":
            self.state = 0
        hub = self.hub
        if hub is None:
            return
        if msg.NAME == "request":  # the message asked for, zero but for the state
            cls = M.MESSAGES[msg.msg_id]
            vals = {f.name: (bytes(f.size) if f.is_raw else 0) for f in cls.FIELDS}
            if "state" in vals:
                vals["state"] = self.state
            if cls.NAME == "version":  # this host's own identity: a matching board
                from host.link import identity

                vals.update(fw_version=identity.fw_version(), table_hash=identity.table_hash(),
                            param_hash=identity.param_hash())
            reply: M.Message = cls(**vals)
        else:
            reply = M.BY_NAME["ack"](msg_id=msg.ID, seq=seq)
        threading.Thread(target=hub.on_message, args=(reply, seq)).start()

    def _recv_internal(self, timeout: float | None) -> list:
        time.sleep(timeout or 0)
        return []

    def count(self, name: str, since: float = 0.0) -> int:
        return sum(1 for t, n in self.log if n == name and t >= since)


def test_host_heartbeat_only_while_a_live_page_asked_for_the_arm(tmp_path: Path) -> None:
    board = _Board()
    hub = Hub(SharedLink(board), {"mode": "test"}, tmp_path)
    board.hub = hub
    try:
        # no page: nothing is fed, and the arm is refused to anyone but a live page
        for _ in range(5):
            hub.tick_keepalive()
            time.sleep(0.03)
        assert board.count(KEEP) == 0
        with pytest.raises(PermissionError):
            hub.arm("cli")
        page = hub.connect()
        hub.ping(page.id)
        hub.arm(page.id)
        assert hub.feeding and board.state == 2
        # the pump feeds the board while the page pings
        t0 = time.monotonic()
        while time.monotonic() - t0 < 1.5:
            hub.tick_keepalive()
            hub.ping(page.id)
            time.sleep(0.02)
        assert 7 <= board.count(KEEP, t0) <= 22  # every 0.1 s (15 on an idle machine)
        # the page goes silent (a frozen or closed tab): feeding stops, the board is disarmed
        t1 = time.monotonic()
        while hub.feeding and time.monotonic() - t1 < 3:
            hub.tick_keepalive()
            time.sleep(0.02)
        assert not hub.feeding
        gone = time.monotonic() - t1
        assert PAGE_TIMEOUT_S - 0.1 <= gone <= PAGE_TIMEOUT_S + 1.0
        deadline = time.monotonic() + 2
        while board.state != 0 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert board.state == 0 and board.count("disarm", t1) >= 1
        n = board.count(KEEP)
        for _ in range(10):
            hub.tick_keepalive()
            time.sleep(0.02)
        assert board.count(KEEP) == n  # no more heartbeat
        assert "last page closed" in hub.events[-1]["text"]
    finally:
        hub.close()


def test_a_closed_event_stream_disarms_at_once(tmp_path: Path) -> None:
    board = _Board()
    hub = Hub(SharedLink(board), {"mode": "test"}, tmp_path)
    board.hub = hub
    try:
        page = hub.connect()
        hub.ping(page.id)
        hub.arm(page.id)
        t0 = time.monotonic()
        hub.disconnect(page)
        deadline = time.monotonic() + 2
        while board.state != 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert board.state == 0 and time.monotonic() - t0 < 0.5
        assert not hub.feeding and not hub.arm_requested
    finally:
        hub.close()


def test_telemetry_rows_pair_and_count_losses(tmp_path: Path) -> None:
    board = _Board()
    hub = Hub(SharedLink(board), {"mode": "test"}, tmp_path)
    try:
        ts, tc = M.BY_NAME["telem_state"], M.BY_NAME["telem_ctrl"]
        hub.record_start()
        for seq in (1, 2, 4):  # seq 3 lost
            hub.on_message(ts(x=1000 * seq, xdot=0, phi=-20, phidot=0), seq)
            hub.on_message(tc(ref=2000, force=150, duty=-300, step_us=90), seq)
        hub.on_message(ts(x=1, xdot=0, phi=0, phidot=0), 5)  # half a pair
        hub.on_message(tc(ref=0, force=0, duty=0, step_us=0), 6)
        st = hub.record_stop()
        assert st["rows"] == 3 and hub.n == 3
        assert hub.lost == 1 and hub.half_pairs == 1
        lines = hub.record_bytes().decode().splitlines()
        assert lines[0].split(",")[:3] == ["n", "t", "x"]
        first = lines[1].split(",")
        assert [float(v) for v in first[2:10]] == [0.1, 0.0, -0.002, 0.0, 0.2, 1.5, -300, 90]
    finally:
        hub.close()


def test_the_heartbeat_crc_byte_confirms_an_upload_and_flags_another_table(tmp_path: Path) -> None:
    # the heartbeat carries only the low 8 bits of the active table's CRC-16: a heartbeat after an
    # upload must confirm that table, not replace its CRC by one byte (CI caught 116 == 0xF574 & 0xFF)
    board = _Board()
    hub = Hub(SharedLink(board), {"mode": "test"}, tmp_path)
    board.hub = hub
    try:
        hb = M.BY_NAME["heartbeat"]
        vals = {f.name: 0 for f in hb.FIELDS}
        blob = G.design_table("shipped")[0]
        crc = hub.upload_gains(blob, "shipped")
        assert crc == G.M.crc16(blob)
        hub.on_message(hb(**{**vals, "gains_crc": crc & 0xFF}), 1)
        assert hub.gains["crc"] == crc and hub.gains["label"] == "shipped"
        other = (crc + 1) & 0xFF  # the board now runs a table this dashboard did not upload
        hub.on_message(hb(**{**vals, "gains_crc": other}), 2)
        assert hub.gains["crc"] is None and hub.gains["crc_low8"] == other
        assert "reported by the board" in hub.gains["label"]
        hub.on_message(hb(**{**vals, "gains_crc": crc & 0xFF}), 3)  # back to the uploaded one
        assert hub.gains["crc"] == crc and hub.gains["label"] == "shipped"
    finally:
        hub.close()


# ---------------------------------------------------------------- the server, over HTTP
def _req(url: str, data: bytes | None = None, headers: dict | None = None) -> tuple[int, dict]:
    r = urllib.request.Request(url, data=data, headers=headers or {}, method="POST" if data is not None else "GET")
    try:
        with urllib.request.urlopen(r, timeout=10) as res:
            return res.status, json.loads(res.read() or b"{}")
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read() or b"{}")


def test_server_serves_the_page_and_guards_its_commands(tmp_path: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-m", "host.cli.main", "dashboard", "--virtual", "--http-port", "0",
                             "--record-dir", str(tmp_path), "--seconds", "60"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = proc.stdout.readline().strip()  # type: ignore[union-attr]
        assert url.startswith("http://127.0.0.1:")
        page = urllib.request.urlopen(url, timeout=10).read().decode()
        assert "/vendor/uPlot.iife.min.js" in page and "http" not in page.split("<body>")[1].replace("http-", "")
        assert len(urllib.request.urlopen(url + "vendor/uPlot.iife.min.js", timeout=10).read()) > 20000
        # the event stream: hello, then telemetry rows
        with urllib.request.urlopen(url + "events", timeout=10) as es:
            head = es.read(4000).decode()
        assert head.startswith("event: hello") and "event: t" in head
        H = {"X-Upright-Page": "cli", "Content-Type": "application/json"}
        assert _req(url + "api/arm", b"{}")[0] == 403  # no header: no command
        code, body = _req(url + "api/arm", b"{}", H)
        assert code == 403 and "live dashboard page" in body["error"]  # not a live page
        assert _req(url + "api/ping", b"{}", H)[0] == 410
        assert _req(url + "api/record.csv")[0] == 404
        assert _req(url + "api/reference", b'{"x": "nan"}', H)[0] == 400
        code, body = _req(url + "api/reference", b'{"x": 5}', H)
        assert code == 409 and "out_of_range" in body["error"]  # the board's own refusal
        assert _req(url + "api/gains?design=shipped", b"", H)[0] == 200
        bad = urllib.request.Request(url + "api/status", headers={"Host": "evil.example:80"})
        with pytest.raises(urllib.error.HTTPError) as exc:
            urllib.request.urlopen(bad, timeout=10)
        assert exc.value.code == 403
        st = _req(url + "api/status")[1]
        assert st["heartbeat"]["state_name"] == "disarmed" and st["telemetry_rows"] > 10
        assert st["gains"]["crc"] == G.M.crc16(G.design_table("shipped")[0])
    finally:
        proc.send_signal(2)
        proc.wait(timeout=15)


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize("argv, status, text", [
    ([], 2, "one of the arguments"),
    (["--virtual", "--http-port", "70000"], 2, "--http-port"),
    (["--port", "/dev/nonexistent-upright"], 1, "nonexistent-upright"),
    (["--virtual", "--port", "/dev/x"], 2, "not allowed with"),
])
def test_bad_input_is_one_line(argv: list[str], status: int, text: str) -> None:
    r = subprocess.run([sys.executable, "-m", "host.cli.main", "dashboard", *argv], cwd=ROOT,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == status, r.stderr
    assert text in r.stderr and "Traceback" not in r.stderr
