"""The dashboard's HTTP server: stdlib ``http.server`` on 127.0.0.1, Server-Sent Events, a JSON API.

Routes
------
``GET /?token=T``             the page (``static/index.html``, with this run's token in it)
``GET /static/NAME``          the page's script and style
``GET /vendor/NAME``          uPlot's dist files from ``node_modules/uplot/dist`` (``make setup``)
``GET /events``               the event stream: ``hello`` (connection, tables, the page's id),
                              ``t`` (one telemetry row + its receive time), ``hb`` (state or
                              fault flags changed), ``note``, ``gains``
``POST /api/ping``            the page is alive; carries its screen-update times and latencies
``GET /api/status``           board state, link and page figures, recording, measurements
``POST /api/arm|disarm|clear``  commands (arm only from a live page)
``POST /api/reference``       ``{"x": m}``: a reference step
``POST /api/square``          ``{"amplitude", "period", "low"}`` or ``{"stop": true}``
``POST /api/gains``           ``?design=shipped|place``, or ``?file=NAME`` with the file as body
``POST /api/record/start|stop``, ``GET /api/record.csv``  recording and its download
``POST /api/upright``         ``--virtual``: stand the pendulum up (motor off only)

Who may command the board
-------------------------
* The ``Host`` header must name this machine (no DNS rebinding), and a request that carries an
  ``Origin`` must come from this server's own origin.
* Each run draws a random token (:attr:`DashboardServer.token`, 192 bits).  The address the
  dashboard prints carries it (``/?token=...``); the page is served only to a request that
  carries it, and has it embedded; every ``POST`` must send it in the header
  :data:`TOKEN_HEADER` -- so only the page this run served (and whoever read the printed
  address) can disarm, clear, set the reference or upload gains, not any other local process.
  A browser sends such a header cross-origin only after a CORS preflight, which this server
  never grants.  Refused: 403, one line.
* Every ``POST`` also names its page (``X-Upright-Page``: the id of the page's event stream,
  or ``cli``); arming needs a live page.

Bad requests
------------
Every request that is not well formed is answered in one line, ``{"error": "..."}``, and
nothing reaches the board (:mod:`host.dashboard.request`): 411 without ``Content-Length``,
400 for a negative or non-numeric one or a short body, 413 beyond the size limit, 400 for a
body that is not a JSON object, an unknown or missing key, a value of the wrong type, not
finite or out of range; the server's own HTTP errors (414, 431, 501...) are one line too.  A
connection idle for :data:`~host.dashboard.request.REQUEST_TIMEOUT_S` is closed (a request
left half-sent gets 408), so no handler thread waits forever, and at most
:data:`MAX_CONNECTIONS` are served at once (503 beyond).
"""
from __future__ import annotations

import hmac
import json
import secrets
import socket
import sys
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from host.dashboard import request as R
from host.dashboard.gains import TableError, design_table, table_bytes
from host.dashboard.hub import Hub
from host.link.clients import CommandRefused, LinkError, LinkTimeout
from host.operate.board import BoardError

__all__ = ["DashboardServer", "STATIC", "VENDOR", "TOKEN_HEADER", "PAGE_HEADER", "MAX_CONNECTIONS", "split_url"]

_HERE = Path(__file__).resolve().parent
STATIC = _HERE / "static"
VENDOR = _HERE.parent.parent / "node_modules" / "uplot" / "dist"
TOKEN_HEADER = "X-Upright-Token"
"""The header every ``POST`` carries this run's token in."""
PAGE_HEADER = "X-Upright-Page"
"""The header naming the page (its event stream's id) a ``POST`` comes from."""
MAX_CONNECTIONS = 64
"""Connections served at once (an open page holds one for its event stream and a few for fetches)."""
_TOKEN_SLOT = b"__UPRIGHT_TOKEN__"
_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
          ".css": "text/css; charset=utf-8", ".png": "image/png"}
_GAINS_QUERY = ("design", "file")


def split_url(url: str) -> tuple[str, str]:
    """``(base, token)`` of the address ``upright dashboard`` prints (``http://127.0.0.1:P/?token=T``)."""
    parts = urlsplit(url)
    token = parse_qs(parts.query).get("token", [""])[-1]
    return f"{parts.scheme}://{parts.netloc}/", token


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


class _Handler(BaseHTTPRequestHandler):
    server: "DashboardServer"
    server_version = "upright-dashboard"
    protocol_version = "HTTP/1.1"  # keep-alive (every answer has a Content-Length)
    timeout = R.REQUEST_TIMEOUT_S  # socket timeout: an idle connection is closed

    def log_message(self, fmt: str, *args: Any) -> None:  # quiet: the console is the user's
        pass

    def log_request(self, code: Any = "-", size: Any = "-") -> None:
        pass

    # ------------------------------------------------------------------ helpers
    def _send(self, status: int, body: bytes, ctype: str, extra: dict[str, str] | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("Referrer-Policy", "no-referrer")
        self.send_header("X-Content-Type-Options", "nosniff")
        if self.close_connection:
            self.send_header("Connection", "close")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, obj: Any, status: int = 200) -> None:
        self._send(status, json.dumps(obj).encode(), "application/json")

    def _error(self, status: int, text: str, *, close: bool = False) -> None:
        # one line, JSON; the connection closes where the rest of the request was not read
        if close or not getattr(self, "_body_done", True) or status >= 500 or status in (408, 411, 413):
            self.close_connection = True
        self._json({"error": _one_line(text)}, status)

    def send_error(self, code: int, message: str | None = None, explain: str | None = None) -> None:
        """http.server's own errors (bad request line, 414, 431, 501...): one line of JSON too."""
        short = self.responses.get(code, ("error", ""))[0]
        self.close_connection = True
        if getattr(self, "request_version", "HTTP/0.9") not in ("HTTP/1.0", "HTTP/1.1"):
            self.request_version = "HTTP/1.1"  # a status line and headers, even for a garbled request line
        try:
            self._error(code, f"{short}: {message}" if message and message != short else short, close=True)
        except OSError:
            pass

    def handle_one_request(self) -> None:
        """One request; as http.server's, but a request left half-sent (idle for the socket timeout,
        or its line and headers not complete within :data:`~host.dashboard.request.HEAD_TIMEOUT_S`)
        is answered 408 before the connection is closed, and nothing escapes as a traceback."""
        started = False
        self._answered = False
        self._body_done = True
        self._reaped = False
        self.server.head_started(self)
        try:
            try:
                self.raw_requestline = self.rfile.readline(65537)
                started = bool(self.raw_requestline)
                if self._reaped:
                    raise TimeoutError
                if len(self.raw_requestline) > 65536:
                    self.requestline = self.request_version = self.command = ""
                    self.send_error(HTTPStatus.REQUEST_URI_TOO_LONG, "request line too long")
                    return
                if not self.raw_requestline:
                    self.close_connection = True
                    return
                if not self.parse_request():
                    return
                if self._reaped:
                    raise TimeoutError
            finally:
                self.server.head_done(self)
            method = getattr(self, "do_" + self.command, None)
            if method is None:
                self.send_error(HTTPStatus.NOT_IMPLEMENTED, f"method {self.command[:20]!r} not supported")
                return
            method()
            self.wfile.flush()
        except TimeoutError:
            self.close_connection = True
            if started and not self._answered:
                for k, v in (("command", ""), ("request_version", "HTTP/1.1"), ("requestline", "")):
                    if not hasattr(self, k):
                        setattr(self, k, v)
                why = (f"request line and headers not complete within {R.HEAD_TIMEOUT_S:g} s" if self._reaped
                       else f"nothing more came within {self.timeout:g} s")
                try:
                    self._error(408, f"request timed out: {why}", close=True)
                except OSError:
                    pass
        except OSError:  # the client went away
            self.close_connection = True

    def reap(self) -> None:
        """The request's line and headers took too long: end the read (the server's reaper thread)."""
        self._reaped = True
        try:
            self.connection.shutdown(socket.SHUT_RD)
        except OSError:
            pass

    def send_response(self, code: int, message: str | None = None) -> None:
        self._answered = True
        super().send_response(code, message)

    def _host_ok(self) -> bool:
        host = (self.headers.get("Host") or "").rsplit(":", 1)[0].strip("[]")
        return host in ("127.0.0.1", "localhost", "::1")

    def _origin_ok(self) -> bool:
        origin = self.headers.get("Origin")
        if origin is None:
            return True
        o = urlsplit(origin)
        host, port = self.server.server_address[:2]
        return o.scheme == "http" and o.hostname in ("127.0.0.1", "localhost", "::1") and o.port == port

    def _token_ok(self, given: str | None) -> bool:
        return bool(given) and hmac.compare_digest(str(given).encode(), self.server.token.encode())

    def _file(self, path: Path, token: bool = False) -> None:
        try:
            data = path.read_bytes()
        except OSError:
            if path.parent == VENDOR:
                self._error(500, f"{path.name} missing: run `make setup` (npm ci installs uPlot into node_modules)")
            else:
                self._error(404, "not found")
            return
        if token:
            data = data.replace(_TOKEN_SLOT, self.server.token.encode())
        self._send(200, data, _TYPES.get(path.suffix, "application/octet-stream"))

    # ------------------------------------------------------------------ GET
    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        self._answered = False
        try:
            self._get()
        except OSError:
            self.close_connection = True
        except Exception as exc:  # noqa: BLE001 - one line, never a traceback on the console
            self.server.internal_error(f"GET {self.path[:80]}", exc)
            if not self._answered:
                self._error(500, f"internal error: {type(exc).__name__}: {exc}")

    do_HEAD = do_GET

    def _get(self) -> None:
        if (self.headers.get("Content-Length") or "0").strip() != "0" or self.headers.get("Transfer-Encoding"):
            self._body_done = False  # a GET's body is not read: the connection closes after the answer
        if not self._host_ok():
            self._error(403, "bad Host header: the dashboard answers only to 127.0.0.1 / localhost")
            return
        url = urlsplit(self.path)
        p = url.path
        hub = self.server.hub
        if p in ("/", "/index.html"):
            token = parse_qs(url.query).get("token", [None])[-1]
            if not self._token_ok(token):
                self._error(403, "open the address upright dashboard printed: the page needs this run's token "
                                 "(?token=...)" + (" -- this one is wrong" if token else ""))
                return
            self._file(STATIC / "index.html", token=True)
        elif p.startswith("/static/") and "/" not in p[8:] and ".." not in p:
            self._file(STATIC / p[8:])
        elif p.startswith("/vendor/") and "/" not in p[8:] and ".." not in p:
            self._file(VENDOR / p[8:])
        elif p == "/events" and self.command == "GET":
            self._events()
        elif p == "/api/status":
            self._json(hub.status())
        elif p == "/api/record.csv":
            data = hub.record_bytes()
            if data is None:
                self._error(404, "nothing recorded yet")
                return
            name = Path(hub.record_status()["path"] or "recording.csv").name
            self._send(200, data, "text/csv; charset=utf-8", {"Content-Disposition": f'attachment; filename="{name}"'})
        else:
            self._error(404, "not found")

    def _events(self) -> None:
        hub = self.server.hub
        c = hub.connect()
        self.close_connection = True  # the stream ends with the connection
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        try:
            while not hub.stopping.is_set() and not self.server.closing:
                evs = c.take(0.5)
                if not evs:
                    self.wfile.write(b": idle\n\n")
                else:
                    self.wfile.write("".join(e for _, e in evs).encode())
                self.wfile.flush()
                for t_rx, _ in evs:
                    if t_rx is not None:
                        hub.pushed(t_rx)
        except OSError:  # the page went away (BrokenPipe, ConnectionReset) or stopped reading (timeout)
            pass
        finally:
            hub.disconnect(c)

    # ------------------------------------------------------------------ POST
    def do_POST(self) -> None:  # noqa: N802
        self._answered = False
        try:
            self._post()
        except R.BadRequest as exc:
            self._error(exc.status, exc.text)
        except OSError:
            self.close_connection = True
        except Exception as exc:  # noqa: BLE001 - one line, never a traceback on the console
            self.server.internal_error(f"POST {self.path[:80]}", exc)
            if not self._answered:
                self._error(500, f"internal error: {type(exc).__name__}: {exc}")

    def _post(self) -> None:
        self._body_done = False
        # who: this machine, this origin, this run's page -- before a byte of the body is read
        if not self._host_ok():
            self._error(403, "bad Host header: the dashboard answers only to 127.0.0.1 / localhost", close=True)
            return
        if not self._origin_ok():
            self._error(403, f"cross-origin command refused (Origin {self.headers.get('Origin', '')[:60]})", close=True)
            return
        if not self._token_ok(self.headers.get(TOKEN_HEADER)):
            why = "wrong" if self.headers.get(TOKEN_HEADER) else "missing"
            self._error(403, f"commands need this run's token in the {TOKEN_HEADER} header ({why}): "
                             "they are taken only from the page the dashboard served", close=True)
            return
        cid = self.headers.get(PAGE_HEADER)
        if not cid:
            self._error(403, f"commands need the {PAGE_HEADER} header (the page's id, or cli)", close=True)
            return
        url = urlsplit(self.path)
        p = url.path
        if p != "/api/gains" and p not in R.ROUTES:
            self._error(404, "not found", close=True)
            return
        query = parse_qs(url.query, keep_blank_values=True)
        allowed = _GAINS_QUERY if p == "/api/gains" else ()
        for k, v in query.items():
            if k not in allowed:
                raise R.BadRequest(400, f"unknown query parameter {k!r} for {p}"
                                        + (f" (known: {', '.join(allowed)})" if allowed else ""))
            if len(v) > 1:
                raise R.BadRequest(400, f"query parameter {k!r} given twice")
        q = {k: v[-1] for k, v in query.items()}
        # what: a whole body of a declared, bounded length, within the time limit
        try:
            n = R.content_length(self.headers)
        except R.BadRequest:
            self.close_connection = True
            raise
        try:
            body = R.read_body(self.rfile, self.connection, n)
        except R.BadRequest:
            self.close_connection = True
            raise
        self._body_done = True
        hub = self.server.hub
        try:
            if p == "/api/gains":
                if "design" in q and "file" in q:
                    raise R.BadRequest(400, "/api/gains: give design or file, not both")
                if "design" in q:
                    if body:
                        raise R.BadRequest(400, "/api/gains?design=...: no body expected")
                    blob, label = design_table(q["design"])
                else:
                    blob, label = table_bytes(body, q.get("file", "file")[:80] or "file")
                self._json({"crc": hub.upload_gains(blob, label), "label": label})
                return
            args = R.json_args(p, body)
            if p == "/api/ping":
                ok = hub.ping(cid, args)
                self._json({"ok": ok, "feeding": hub.feeding, "stats": hub.stats(), "record": hub.record_status()},
                           200 if ok else 410)
                return
            if p == "/api/arm":
                hub.arm(cid)
            elif p == "/api/disarm":
                hub.disarm(cid)
            elif p == "/api/clear":
                hub.clear()
            elif p == "/api/reference":
                hub.set_reference(args["x"])
            elif p == "/api/square":
                if args.get("stop"):
                    hub.stop_square()
                else:
                    hub.square(args.get("amplitude", 0.2), args.get("period", 4.4), args.get("low", 0.0))
            elif p == "/api/record/start":
                self._json({"path": str(hub.record_start())})
                return
            elif p == "/api/record/stop":
                self._json(hub.record_stop())
                return
            elif p == "/api/upright":
                if hub.virtual is None:
                    self._error(409, "only the virtual pendulum can be stood up from here")
                    return
                st = (hub.heartbeat or {}).get("state")
                if st in (1, 2):
                    self._error(409, "disarm first: the motor is on")
                    return
                hub.virtual.reset()
            self._json({"ok": True, "heartbeat": hub._hb_payload()})
        except PermissionError as exc:
            self._error(403, str(exc))
        except (CommandRefused, BoardError) as exc:
            self._error(409, str(exc))
        except LinkTimeout as exc:
            self._error(504, f"the board did not answer: {exc}")
        except LinkError as exc:
            self._error(502, f"link failed: {exc}")
        except R.BadRequest:
            raise
        except (TableError, ValueError, KeyError, TypeError) as exc:
            self._error(400, f"bad request: {exc}")


class DashboardServer(ThreadingHTTPServer):
    """The dashboard's HTTP server on ``host:port`` (port 0: any free one).

    :attr:`url` is its base address, :attr:`page_url` the page's address with this run's
    :attr:`token` (what ``upright dashboard`` prints).
    """

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, hub: Hub, host: str = "127.0.0.1", port: int = 8765, *, token: str | None = None) -> None:
        super().__init__((host, port), _Handler)
        self.hub = hub
        self.token = token or secrets.token_urlsafe(24)
        self.closing = False
        self.internal_errors = 0
        self._thread: threading.Thread | None = None
        self._conn_lock = threading.Lock()
        self.connections = 0
        self.refused_busy = 0
        self.reaped = 0
        self._heads: dict[int, tuple[float, Any]] = {}

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        return f"http://{host}:{port}/"

    @property
    def page_url(self) -> str:
        return f"{self.url}?token={self.token}"

    def internal_error(self, where: str, exc: BaseException) -> None:
        """An unexpected exception in a handler: one line on stderr (the request got a 500)."""
        self.internal_errors += 1
        print(f"upright dashboard: internal error in {where}: {type(exc).__name__}: {_one_line(str(exc))[:200]}",
              file=sys.stderr, flush=True)

    def handle_error(self, request: Any, client_address: Any) -> None:
        exc = sys.exc_info()[1]
        if exc is not None and not isinstance(exc, OSError):
            self.internal_error("a connection", exc)

    def process_request(self, request: Any, client_address: Any) -> None:
        with self._conn_lock:
            busy = self.connections >= MAX_CONNECTIONS
            if not busy:
                self.connections += 1
        if busy:
            self.refused_busy += 1
            body = json.dumps({"error": f"too many connections (at most {MAX_CONNECTIONS})"}).encode()
            try:
                request.settimeout(1.0)
                request.sendall(b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
                                b"Content-Length: %d\r\nConnection: close\r\n\r\n%s" % (len(body), body))
            except OSError:
                pass
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            with self._conn_lock:
                self.connections -= 1
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            with self._conn_lock:
                self.connections -= 1

    def head_started(self, handler: Any) -> None:
        """A handler starts reading a request's line and headers (the reaper watches it)."""
        with self._conn_lock:
            self._heads[id(handler)] = (time.monotonic() + R.HEAD_TIMEOUT_S, handler)

    def head_done(self, handler: Any) -> None:
        with self._conn_lock:
            self._heads.pop(id(handler), None)

    def _reaper(self) -> None:
        # ends the read of any request whose line and headers trickle in for longer than
        # HEAD_TIMEOUT_S (the socket timeout alone bounds only the gap between two bytes)
        while not self.closing:
            time.sleep(0.25)
            now = time.monotonic()
            with self._conn_lock:
                late = [h for t, h in self._heads.values() if now > t]
                for h in late:
                    self._heads.pop(id(h), None)
            for h in late:
                self.reaped += 1
                h.reap()

    def start(self) -> "DashboardServer":
        self._thread = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.1},
                                        name="dashboard-http", daemon=True)
        self._thread.start()
        threading.Thread(target=self._reaper, name="dashboard-reaper", daemon=True).start()
        return self

    def stop(self) -> None:
        self.closing = True
        self.shutdown()
        self.server_close()
        time.sleep(0.05)
