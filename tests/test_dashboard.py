"""``upright dashboard`` without a browser: gain tables, the watchdog policy, the HTTP guards, bad input, signals.

The policy test drives :class:`host.dashboard.hub.Hub` over a scripted link that answers every
command (no board needed): no page, no host heartbeat; a live page's arm starts it; the page
going silent stops it and disarms.  The server tests run ``upright dashboard --virtual`` (one
process for the module) and talk to it over HTTP and raw sockets: the page only at the printed
address (its token), commands only with the token, every malformed request answered in one
line, idle and stalled connections let go.  Each signal test starts its own dashboard, arms the
virtual board from a live page and ends the dashboard with SIGINT, SIGTERM or SIGHUP: the board
must be disarmed, by its own word, before the exit.  The browser test is
tests/test_dashboard_browser.py.
"""

from __future__ import annotations

import csv
import json
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Iterator
from urllib.parse import urlsplit

import pytest

import tool_helpers as TH
from host.dashboard import gains as G
from host.dashboard.hub import COLUMNS, PAGE_TIMEOUT_S, Hub
from host.dashboard.server import PAGE_HEADER, TOKEN_HEADER, split_url
from host.link import messages as M
from host.link.clients import Link

ROOT = Path(__file__).resolve().parent.parent
# the frame that feeds the board's watchdog
KEEP = "host_heartbeat"


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


@pytest.fixture
def linked(tmp_path: Path) -> Iterator[tuple[_Board, Hub]]:
    """A hub on a :class:`_Board` that answers through it; closed at the end."""
    board = _Board()
    hub = Hub(board, {"mode": "test"}, tmp_path)
    board.hub = hub
    try:
        yield board, hub
    finally:
        hub.close()


@pytest.mark.slow
def test_host_heartbeat_only_while_a_live_page_asked_for_the_arm(linked: tuple[_Board, Hub]) -> None:
    board, hub = linked
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


def test_a_closed_event_stream_disarms_at_once(linked: tuple[_Board, Hub]) -> None:
    board, hub = linked
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


def test_telemetry_rows_pair_and_count_losses(linked: tuple[_Board, Hub]) -> None:
    _, hub = linked
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


def test_the_heartbeat_crc_byte_confirms_an_upload_and_flags_another_table(linked: tuple[_Board, Hub]) -> None:
    # the heartbeat carries only the low 8 bits of the active table's CRC-16: a heartbeat after an
    # upload must confirm that table, not replace its CRC by one byte (CI caught 116 == 0xF574 & 0xFF)
    _, hub = linked
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


# ---------------------------------------------------------------- the server, over HTTP
_req = TH.http_json


class _Served:
    """``upright dashboard --virtual`` in its own process: the printed address, its base and token."""

    def __init__(self, tmp: Path, seconds: float | None = 120.0) -> None:
        argv = [sys.executable, "-m", "host.cli.main", "dashboard", "--virtual", "--http-port", "0",
                "--record-dir", str(tmp)]
        if seconds is not None:
            argv += ["--seconds", str(seconds)]
        self.proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.page_url = self.proc.stdout.readline().strip()  # type: ignore[union-attr]
        assert self.page_url.startswith("http://127.0.0.1:"), self._fail()
        self.url, self.token = split_url(self.page_url)
        assert len(self.token) >= 32 and self.page_url == f"{self.url}?token={self.token}"
        host, port = urlsplit(self.url).hostname, urlsplit(self.url).port
        self.addr = (str(host), int(port or 0))

    def _fail(self) -> str:
        if self.proc.poll() is not None:
            return self.proc.stderr.read()  # type: ignore[union-attr]
        return "no address printed"

    def headers(self, page: str = "cli", **extra: str) -> dict[str, str]:
        return {PAGE_HEADER: page, TOKEN_HEADER: self.token, "Content-Type": "application/json", **extra}

    def post(self, path: str, body: dict | bytes | None = None, page: str = "cli") -> tuple[int, dict]:
        data = body if isinstance(body, bytes) else json.dumps(body or {}).encode()
        return _req(self.url + path, data, self.headers(page))

    def stop(self, sig: int = signal.SIGINT, timeout: float = 20.0) -> tuple[int, str]:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            _, err = self.proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            _, err = self.proc.communicate()
        return self.proc.returncode, err


def _raw(addr: tuple[str, int], data: bytes, *, shut: bool = False, timeout: float = 20.0) -> tuple[int, dict, float]:
    """Send bytes as they are (a request no client library would send); the answer's status, its
    JSON body (one line) and the seconds it took."""
    t0 = time.monotonic()
    with socket.create_connection(addr, timeout=timeout) as s:
        s.sendall(data)
        if shut:
            s.shutdown(socket.SHUT_WR)
        resp = b""
        while b"\r\n\r\n" not in resp:
            chunk = s.recv(65536)
            if not chunk:
                return 0, {}, time.monotonic() - t0  # closed without an answer
            resp += chunk
        head, _, body = resp.partition(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        hdr = {k.lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:])}
        n = int(hdr["content-length"])
        while len(body) < n:
            chunk = s.recv(65536)
            if not chunk:
                break
            body += chunk
    assert len(body) == n and body.count(b"\n") == 0, body  # one line
    return int(lines[0].split()[1]), json.loads(body), time.monotonic() - t0


def _post_bytes(served: _Served, path: str, body: bytes, *, length: str | None = "auto",
                headers: dict[str, str] | None = None) -> bytes:
    h = {"Host": f"127.0.0.1:{served.addr[1]}", PAGE_HEADER: "cli", TOKEN_HEADER: served.token,
         "Content-Type": "application/json", **(headers or {})}
    if length == "auto":
        h["Content-Length"] = str(len(body))
    elif length is not None:
        h["Content-Length"] = length
    h = {k: v for k, v in h.items() if v is not None}
    return (f"POST {path} HTTP/1.1\r\n" + "".join(f"{k}: {v}\r\n" for k, v in h.items()) + "\r\n").encode() + body


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory):
    s = _Served(tmp_path_factory.mktemp("dash"))
    try:
        yield s
    finally:
        code, err = s.stop()
    assert "Traceback" not in err and "internal error" not in err, err[-3000:]


@pytest.mark.slow
def test_server_serves_the_page_and_guards_its_commands(served: _Served) -> None:
    url = served.url
    page = urllib.request.urlopen(served.page_url, timeout=10).read().decode()
    assert "/vendor/uPlot.iife.min.js" in page and "http" not in page.split("<body>")[1].replace("http-", "")
    # the page carries this run's token, and is served only to the address that carries it
    assert f'<meta name="upright-token" content="{served.token}">' in page
    for bad in (url, url + "?token=" + "x" * len(served.token), url + "index.html"):
        code, body = _req(bad)
        assert code == 403 and "token" in body["error"], (bad, body)
    assert len(urllib.request.urlopen(url + "vendor/uPlot.iife.min.js", timeout=10).read()) > 20000
    app = urllib.request.urlopen(url + "static/app.js", timeout=10).read().decode()
    assert app.count(f'"{TOKEN_HEADER}": TOKEN') == 2  # both the commands and the ping send it
    # the event stream: hello, then telemetry rows
    with urllib.request.urlopen(url + "events", timeout=10) as es:
        head = es.read(4000).decode()
    assert head.startswith("event: hello") and "event: t" in head
    code, body = served.post("api/arm")
    assert code == 403 and "live dashboard page" in body["error"]  # not a live page
    assert served.post("api/ping")[0] == 410
    assert _req(url + "api/record.csv")[0] == 404
    code, body = served.post("api/reference", {"x": 0.9})
    assert code == 409 and "out_of_range" in body["error"]  # the board's own refusal (ref_limit_um 0.8 m)
    assert served.post("api/reference", {"x": 0.0})[0] == 200
    assert served.post("api/disarm")[0] == 200 and served.post("api/clear")[0] == 200
    assert _req(url + "api/gains?design=shipped", b"", served.headers())[0] == 200
    bad = urllib.request.Request(url + "api/status", headers={"Host": "evil.example:80"})
    with pytest.raises(urllib.error.HTTPError) as exc:
        urllib.request.urlopen(bad, timeout=10)
    assert exc.value.code == 403
    st = _req(url + "api/status")[1]
    assert st["heartbeat"]["state_name"] == "disarmed" and st["telemetry_rows"] > 10
    assert st["gains"]["crc"] == G.M.crc16(G.design_table("shipped")[0])


@pytest.mark.parametrize("path", ["api/disarm", "api/clear", "api/reference", "api/gains?design=shipped",
                                  "api/arm", "api/ping", "api/record/start", "api/square"])
@pytest.mark.parametrize("who", ["no token", "wrong token", "no page", "foreign origin", "foreign host"])
def test_commands_only_from_the_page_it_served(served: _Served, path: str, who: str) -> None:
    # any other local process (it knows the routes and a page id, not the token) is refused: 403, one line
    h = {"no token": {TOKEN_HEADER: None}, "wrong token": {TOKEN_HEADER: served.token[:-1] + ("B" if served.token.endswith("A") else "A")},
         "no page": {PAGE_HEADER: None}, "foreign origin": {"Origin": "http://127.0.0.1:1"},
         "foreign host": {"Host": "evil.example"}}[who]
    body = b'{"x": 0.1}' if path == "api/reference" else b"{}"
    code, ans, _ = _raw(served.addr, _post_bytes(served, "/" + path, body, headers=h))
    assert code == 403, ans
    word = {"no token": "token", "wrong token": "token", "no page": PAGE_HEADER, "foreign origin": "Origin",
            "foreign host": "Host"}[who]
    assert word in ans["error"]


_REF = "/api/reference"
MALFORMED = [
    # (name, path, body, Content-Length ("auto" = the body's), extra headers, status, words in the answer)
    ("no Content-Length", "/api/disarm", b"", None, {}, 411, "Content-Length required"),
    ("chunked", "/api/disarm", b"0\r\n\r\n", None, {"Transfer-Encoding": "chunked"}, 411, "Transfer-Encoding"),
    ("negative Content-Length", "/api/disarm", b"", "-1", {}, 400, "negative"),
    ("Content-Length not a number", "/api/disarm", b"", "12abc", {}, 400, "not a number"),
    ("oversized Content-Length", "/api/gains?file=g.py", b"", str(10**9), {}, 413, "too large"),
    ("short body, closed", _REF, b'{"x": 0', "20", {}, 400, "7 of 20 bytes before the connection closed"),
    ("not JSON", _REF, b'{"x": ', "auto", {}, 400, "not JSON"),
    ("not UTF-8", _REF, b'{"x": "\xff"}', "auto", {}, 400, "UTF-8"),
    ("NaN literal", _REF, b'{"x": NaN}', "auto", {}, 400, "NaN is not a JSON number"),
    ("Infinity literal", _REF, b'{"x": -Infinity}', "auto", {}, 400, "-Infinity is not a JSON number"),
    ("overflowing float", _REF, b'{"x": 1e999}', "auto", {}, 400, "x must be finite"),
    ("absurd float", _REF, b'{"x": 1e308}', "auto", {}, 400, "x = 1e+308 m is out of range"),
    ("absurd int", _REF, b'{"x": ' + b"9" * 400 + b"}", "auto", {}, 400, "out of range"),
    ("huge int", _REF, b'{"x": ' + b"9" * 5000 + b"}", "auto", {}, 400, "not JSON"),
    ("bool for a number", _REF, b'{"x": true}', "auto", {}, 400, "x must be a number, got bool"),
    ("string for a number", _REF, b'{"x": "0.1"}', "auto", {}, 400, "x must be a number, got str"),
    ("missing key", _REF, b"{}", "auto", {}, 400, "missing key 'x'"),
    ("unknown key", _REF, b'{"x": 0.1, "y": 1}', "auto", {}, 400, "unknown key 'y'"),
    ("repeated key", _REF, b'{"x": 0.1, "x": 0.7}', "auto", {}, 400, "given twice"),
    ("array body", _REF, b"[0.1]", "auto", {}, 400, "must be a JSON object, got list"),
    ("nested too deep", _REF, b"[" * 100000 + b"]" * 100000, "auto", {}, 400, "not JSON"),
    ("body on a bare command", "/api/arm", b'{"force": 1}', "auto", {}, 400, "unknown key 'force'"),
    ("square period", "/api/square", b'{"amplitude": 0.2, "period": 0}', "auto", {}, 400, "period = 0 s is out of range"),
    ("square top", "/api/square", b'{"amplitude": 0.8, "low": 0.5}', "auto", {}, 400, "low + amplitude = 1.3 m"),
    ("square stop", "/api/square", b'{"stop": "yes"}', "auto", {}, 400, "stop must be true or false"),
    ("ping samples", "/api/ping", b'{"latency_ms": 5}', "auto", {}, 400, "latency_ms must be a list"),
    ("ping sample", "/api/ping", b'{"updates": [1, "a"]}', "auto", {}, 400, "updates[1] must be a number"),
    ("unknown query", "/api/disarm?now=1", b"", "auto", {}, 400, "unknown query parameter 'now'"),
    ("gains: design and body", "/api/gains?design=shipped", b"abc", "auto", {}, 400, "no body expected"),
    ("gains: not a table", "/api/gains?file=g.bin", b"abc", "auto", {}, 400, "not a gain table"),
    ("gains: unknown design", "/api/gains?design=nope", b"", "auto", {}, 400, "unknown table"),
    ("unknown route", "/api/selfdestruct", b"", "auto", {}, 404, "not found"),
]


@pytest.mark.parametrize("name, path, body, length, extra, status, words", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_every_malformed_request_is_answered_in_one_line(served: _Served, name: str, path: str, body: bytes,
                                                        length: str | None, extra: dict, status: int,
                                                        words: str) -> None:
    code, ans, took = _raw(served.addr, _post_bytes(served, path, body, length=length, headers=extra),
                           shut=name.startswith("short body"))
    assert code == status, ans
    assert words in ans["error"], ans
    assert took < 4.0  # answered at once, not after a timeout
    # the server lives on, the board untouched
    st = _req(served.url + "api/status")[1]
    assert st["heartbeat"]["state_name"] == "disarmed" and st["heartbeat"]["faults"] == 0


def test_the_servers_own_http_errors_are_one_line(served: _Served) -> None:
    host = f"Host: 127.0.0.1:{served.addr[1]}\r\n"
    code, ans, _ = _raw(served.addr, b"PUT /api/disarm HTTP/1.1\r\n" + host.encode() + b"Content-Length: 0\r\n\r\n")
    assert code == 501 and "PUT" in ans["error"]
    code, ans, _ = _raw(served.addr, b"GET /" + b"a" * 70000 + b" HTTP/1.1\r\n\r\n")
    assert code == 414
    code, ans, _ = _raw(served.addr, b"GET / HTTP/1.1\r\n" + b"".join(b"X-%d: 1\r\n" % i for i in range(120)) + b"\r\n")
    assert code == 431
    code, ans, _ = _raw(served.addr, b"BREW /pot HTCPCP/1.0\r\n\r\n")
    assert code == 400


@pytest.mark.slow
def test_idle_and_stalled_requests_time_out(served: _Served) -> None:
    # a short body that never completes, headers that never end, a connection that says nothing:
    # each is let go after REQUEST_TIMEOUT_S (5 s), the first two answered in one line; headers
    # that trickle in a byte a second are cut at HEAD_TIMEOUT_S (10 s) with a 408; the server
    # answers others meanwhile -- no handler thread waits forever
    results: dict[str, tuple[int, dict, float]] = {}
    stalls = {
        "short body": _post_bytes(served, _REF, b'{"x": 0', length="20"),
        "headers": b"POST /api/disarm HTTP/1.1\r\nHost: 127.0.0.1\r\n",
        "silent": b"",
    }
    threads = [threading.Thread(target=lambda k=k, d=d: results.__setitem__(k, _raw(served.addr, d)))
               for k, d in stalls.items()]

    def trickle() -> None:  # headers one byte a second: never idle for 5 s, never complete
        t0 = time.monotonic()
        with socket.create_connection(served.addr, timeout=30) as s:
            try:
                for b in b"POST /api/disarm HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: " + b"a" * 60:
                    s.sendall(bytes([b]))
                    time.sleep(1.0)
            except OSError:  # the server closed its side
                pass
            resp = b""
            try:
                while chunk := s.recv(4096):
                    resp += chunk
            except OSError:
                pass
        results["trickle"] = (int(resp.split()[1]) if resp else 0, json.loads(resp.partition(b"\r\n\r\n")[2] or b"{}"),
                              time.monotonic() - t0)

    threads.append(threading.Thread(target=trickle))
    for t in threads:
        t.start()
    time.sleep(0.5)
    assert _req(served.url + "api/status")[0] == 200  # served while three connections stall
    for t in threads:
        t.join(30)
    code, ans, took = results["short body"]
    assert code == 400 and "7 of 20 bytes in 5 s" in ans["error"] and 4.5 < took < 15
    code, ans, took = results["headers"]
    assert code == 408 and "timed out" in ans["error"] and 4.5 < took < 15
    code, ans, took = results["silent"]
    assert code == 0 and 4.5 < took < 15  # closed: nothing to answer
    code, ans, took = results["trickle"]
    assert code == 408 and "not complete within 10 s" in ans["error"] and 9.5 < took < 25, (code, ans, took)


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP], ids=lambda s: s.name)
def test_any_signal_disarms_the_board_before_the_dashboard_exits(tmp_path: Path, sig: signal.Signals) -> None:
    # armed from a live page, recording; the signal: the board is disarmed, by the firmware's own
    # word (its heartbeat and its per-tick answer), before the dashboard exits with 128 + signal
    served = _Served(tmp_path, seconds=None)
    es = None
    try:
        es = urllib.request.urlopen(served.url + "events", timeout=10)
        head = b""
        while b"\n\n" not in head:
            head += es.read1(4096)
        page = json.loads(dict(ln.split(": ", 1) for ln in head.partition(b"\n\n")[0].decode().splitlines())["data"])["id"]
        stop = threading.Event()

        def pinger() -> None:  # what app.js does every 250 ms, and the stream read on
            while not stop.is_set():
                try:
                    served.post("api/ping", {}, page)
                    es.read1(65536)
                except (OSError, ValueError):  # the dashboard has gone
                    return
                stop.wait(0.2)

        threading.Thread(target=pinger, daemon=True).start()
        time.sleep(0.5)
        assert served.post("api/record/start", {}, page)[0] == 200
        code, body = served.post("api/arm", {}, page)
        assert code == 200, body
        t0 = time.monotonic()
        while True:
            st = _req(served.url + "api/status")[1]
            if st["heartbeat"]["state"] in (1, 2) and st["virtual"]["fw_state"] in (1, 2) and st["feeding"]:
                break
            assert time.monotonic() - t0 < 15, st
            time.sleep(0.1)
        time.sleep(0.5)
        rec = Path(st["record"]["path"])
        code, err = served.stop(sig)
        stop.set()
    finally:
        if es is not None:
            es.close()
        served.stop(signal.SIGKILL)
    assert code == (130 if sig == signal.SIGINT else 128 + sig), err
    assert re.search(r"board disarmed in \d+ ms \(its heartbeat: disarmed\)", err), err
    print(sig.name, "->", next(ln for ln in err.splitlines() if "board disarmed" in ln))
    assert "Traceback" not in err
    # the recording (closed after the disarm) shows the board armed, then disarmed at its end
    rows = list(csv.reader(rec.read_text().splitlines()))
    states = [int(r[COLUMNS.index("state")]) for r in rows[1:]]
    assert {1, 2} & set(states) and states[-1] == 0, states[-20:]


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
