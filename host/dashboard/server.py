"""The dashboard's HTTP server: stdlib ``http.server`` on 127.0.0.1, Server-Sent Events, a JSON API.

Routes
------
``GET /``                     the page (``static/index.html``)
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

Every ``POST`` must carry the header ``X-Upright-Page`` (a page's id, or ``cli``): a browser only
sends such a header cross-origin after a CORS preflight, which this server never grants, so no
other web page can command the board.  The ``Host`` header must name this machine.
"""

from __future__ import annotations

import json
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from host.dashboard.gains import TableError, design_table, table_bytes
from host.dashboard.hub import Hub
from host.link.clients import CommandRefused, LinkError, LinkTimeout
from host.operate.board import BoardError

__all__ = ["DashboardServer", "STATIC", "VENDOR"]

_HERE = Path(__file__).resolve().parent
STATIC = _HERE / "static"
VENDOR = _HERE.parent.parent / "node_modules" / "uplot" / "dist"
_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
          ".css": "text/css; charset=utf-8", ".png": "image/png"}
_MAX_BODY = 256 * 1024


class _Handler(BaseHTTPRequestHandler):
    server: "DashboardServer"
    server_version = "upright-dashboard"

    def log_message(self, fmt: str, *args: Any) -> None:  # quiet: the console is the user's
        pass

    # ------------------------------------------------------------------ helpers
    def _send(self, status: int, body: bytes, ctype: str, extra: dict[str, str] | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(body)

    def _json(self, obj: Any, status: int = 200) -> None:
        self._send(status, json.dumps(obj).encode(), "application/json")

    def _error(self, status: int, text: str) -> None:
        self._json({"error": text}, status)

    def _host_ok(self) -> bool:
        host = (self.headers.get("Host") or "").rsplit(":", 1)[0].strip("[]")
        return host in ("127.0.0.1", "localhost", "::1")

    def _body(self) -> bytes:
        n = int(self.headers.get("Content-Length") or 0)
        if n > _MAX_BODY:
            raise ValueError(f"request body of {n} bytes is too large")
        return self.rfile.read(n) if n else b""

    def _file(self, path: Path) -> None:
        try:
            data = path.read_bytes()
        except OSError:
            if path.parent == VENDOR:
                self._error(500, f"{path.name} missing: run `make setup` (npm ci installs uPlot into node_modules)")
            else:
                self._error(404, "not found")
            return
        self._send(200, data, _TYPES.get(path.suffix, "application/octet-stream"))

    # ------------------------------------------------------------------ GET
    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        if not self._host_ok():
            self._error(403, "bad Host header")
            return
        url = urlsplit(self.path)
        p = url.path
        hub = self.server.hub
        if p in ("/", "/index.html"):
            self._file(STATIC / "index.html")
        elif p.startswith("/static/") and "/" not in p[8:] and ".." not in p:
            self._file(STATIC / p[8:])
        elif p.startswith("/vendor/") and "/" not in p[8:] and ".." not in p:
            self._file(VENDOR / p[8:])
        elif p == "/events":
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
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
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
        except OSError:  # the page went away (BrokenPipe, ConnectionReset)
            pass
        finally:
            hub.disconnect(c)

    # ------------------------------------------------------------------ POST
    def do_POST(self) -> None:  # noqa: N802
        if not self._host_ok():
            self._error(403, "bad Host header")
            return
        cid = self.headers.get("X-Upright-Page")
        if not cid:
            self._error(403, "commands need the X-Upright-Page header")
            return
        url = urlsplit(self.path)
        q = {k: v[-1] for k, v in parse_qs(url.query).items()}
        hub = self.server.hub
        try:
            body = self._body()
            p = url.path
            if p == "/api/ping":
                args = json.loads(body or b"{}")
                ok = hub.ping(cid, args if isinstance(args, dict) else None)
                self._json({"ok": ok, "feeding": hub.feeding, "stats": hub.stats(), "record": hub.record_status()},
                           200 if ok else 410)
                return
            if p == "/api/gains":
                if "design" in q:
                    blob, label = design_table(q["design"])
                else:
                    blob, label = table_bytes(body, q.get("file", "file"))
                self._json({"crc": hub.upload_gains(blob, label), "label": label})
                return
            args = json.loads(body or b"{}") if body else {}
            if not isinstance(args, dict):
                raise ValueError("the body must be a JSON object")
            if p == "/api/arm":
                hub.arm(cid)
            elif p == "/api/disarm":
                hub.disarm(cid)
            elif p == "/api/clear":
                hub.clear()
            elif p == "/api/reference":
                hub.set_reference(float(args["x"]))
            elif p == "/api/square":
                if args.get("stop"):
                    hub.stop_square()
                else:
                    hub.square(float(args.get("amplitude", 0.2)), float(args.get("period", 4.4)),
                               float(args.get("low", 0.0)))
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
            else:
                self._error(404, "not found")
                return
            self._json({"ok": True, "heartbeat": hub._hb_payload()})
        except PermissionError as exc:
            self._error(403, str(exc))
        except (CommandRefused, BoardError) as exc:
            self._error(409, str(exc))
        except LinkTimeout as exc:
            self._error(504, f"the board did not answer: {exc}")
        except LinkError as exc:
            self._error(502, f"link failed: {exc}")
        except (TableError, ValueError, KeyError, TypeError) as exc:
            self._error(400, f"bad request: {exc}")


class DashboardServer(ThreadingHTTPServer):
    """The dashboard's HTTP server on ``host:port`` (port 0: any free one); :attr:`url`."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, hub: Hub, host: str = "127.0.0.1", port: int = 8765) -> None:
        super().__init__((host, port), _Handler)
        self.hub = hub
        self.closing = False
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        return f"http://{host}:{port}/"

    def start(self) -> "DashboardServer":
        self._thread = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.1},
                                        name="dashboard-http", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self.closing = True
        self.shutdown()
        self.server_close()
        time.sleep(0.05)
