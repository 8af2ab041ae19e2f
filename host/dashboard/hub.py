"""The dashboard's side of the board link: one owner thread, fan-out, commands, watchdog policy.

One thread owns the link's receive side (the *pump*: :class:`PlainPump` for a board on a port,
or the lockstep plant loop of :mod:`host.dashboard.plant` for ``--virtual``) and hands every
message it reads to :meth:`Hub.on_message` with the time it arrived.  The hub

* pairs ``telem_state`` + ``telem_ctrl`` of one tick into a telemetry row stamped with that
  receive time (epoch ms: the page measures frame-to-screen latency against it), keeps the
  last minute, writes rows to the recording, and queues each row, JSON-encoded once, to every
  connected page (:class:`Client`, read by the Server-Sent Events handler);
* keeps the last heartbeat (state, fault flags, boot, uptime) and link statistics;
* shares the board's one :class:`~host.link.clients.Link` (:meth:`~host.link.clients.Link.share`):
  the pump reads it, commands from any thread go through it (``arm``, ``upload_gains``,
  ``param_get``... with their retries and refusals, by the board library
  :class:`~host.operate.board.Board` on that same link), and the hub delivers every received
  frame but telemetry to them (:meth:`~host.link.clients.Link.deliver`);
* applies the watchdog policy: the host heartbeat (the link's one
  :class:`~host.link.keepalive.Keepalive`, every :data:`KEEPALIVE_S` to a board at full speed and
  in the board's time to a slower one) is sent only while at least one page is
  live (its event stream open and a ping within :data:`PAGE_TIMEOUT_S`) *and* the arm was
  requested from a live page; when the last live page goes, feeding stops and the board is
  disarmed.  A closed page therefore never keeps a board armed: its watchdog
  (``watchdog_ms``) cuts the motor even if the disarm is lost.

The virtual board's sensor frames feed its watchdog by themselves (the host *is* the plant
there); the policy still disarms it when the last page goes.
"""

from __future__ import annotations

import collections
import csv
import json
import math
import threading
import time
from pathlib import Path
from typing import Any, Callable

from firmware import msgtable as T
from host.hil.accounting import TickPairs
from host.link import messages as M
from host.link.clients import Link, LinkError
from host.operate.board import Board, BoardError, fault_names, fault_table
from host.operate.record import TELEMETRY, telemetry_values

__all__ = [
    "KEEPALIVE_S",
    "PAGE_TIMEOUT_S",
    "COLUMNS",
    "Client",
    "Hub",
    "PlainPump",
]

KEEPALIVE_S = 0.1
"""Host heartbeat period while feeding a board at full speed (the board's watchdog default is 250 ms);
a slower board gets one every :data:`host.link.keepalive.KEEPALIVE_BOARD_S` of its clock, at most
this often."""
PAGE_TIMEOUT_S = 1.0
"""A page that has not pinged for this long is not live (pages ping every 250 ms)."""

COLUMNS = ("n", "t", *TELEMETRY, "seq")
"""Columns of a telemetry row (and of the recorded CSV): ``n`` the row's number since the dashboard
started, ``t`` its receive time in s since then, the recorders' telemetry columns
(:data:`host.operate.record.TELEMETRY`: the two frames in physical units, the state and fault flags
of the last heartbeat) and the board's sequence number ``seq`` -- every column of
:data:`host.operate.record.COLUMNS`, so a dashboard recording reads as a board recording."""

_TS = M.BY_NAME["telem_state"]
_TC = M.BY_NAME["telem_ctrl"]
_HB = M.BY_NAME["heartbeat"]
_ACT = M.BY_NAME["hil_actuator"]
_REQUEST = M.BY_NAME["request"]
_PERIODIC = (_TS, _TC, _HB)
_ARMED_STATES = {s[0] for s in T.STATES if s[1] in ("armed", "balancing")}


class Client:
    """One connected page: its event queue and liveness."""

    def __init__(self, cid: str, maxlen: int = 2000) -> None:
        self.id = cid
        self.q: collections.deque[tuple[float | None, str]] = collections.deque(maxlen=maxlen)
        self.cv = threading.Condition()
        self.connected = time.monotonic()
        self.last_ping = time.monotonic()
        self.open = True
        self.dropped = 0

    def push(self, event: str, t_rx: float | None = None) -> None:
        with self.cv:
            if len(self.q) == self.q.maxlen:
                self.dropped += 1
            self.q.append((t_rx, event))
            self.cv.notify()

    def take(self, timeout: float) -> list[tuple[float | None, str]]:
        with self.cv:
            if not self.q:
                self.cv.wait(timeout)
            out = list(self.q)
            self.q.clear()
        return out


def _event(kind: str, data: Any) -> str:
    return f"event: {kind}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


class Hub:
    """State, fan-out, commands and the watchdog policy of one dashboard (see the module docstring).

    Parameters
    ----------
    link : Link
        The board's link, shared from now on (:meth:`~host.link.clients.Link.share`: the pump
        reads it, commands from any thread wait for what the hub delivers).
    info : dict
        What the page shows about the connection (``mode``, ``port``...).
    record_dir : Path
        Where recordings are written.
    gains : dict, optional
        The active gain table as known at start (``crc``, ``label``).
    virtual : object, optional
        The virtual plant (``reset()``), for the page's "put the pendulum back" button.
    keepalive : bool
        Send the host heartbeat while feeding (False where something else feeds the watchdog).
    """

    def __init__(self, link: Link, info: dict[str, Any], record_dir: Path, *,
                 gains: dict[str, Any] | None = None, virtual: Any = None, keepalive: bool = True) -> None:
        self.link = link
        link.share()
        self.info = dict(info)
        self.record_dir = Path(record_dir)
        self.gains = dict(gains or {"crc": None, "label": "unknown (not uploaded by this dashboard)"})
        self.virtual = virtual
        self.keepalive = keepalive
        self.t0_mono = time.monotonic()
        self.t0_wall = time.time()
        self._lock = threading.RLock()
        self.rows: collections.deque[list[float]] = collections.deque(maxlen=3000)
        self.n = 0
        self.heartbeat: dict[str, int] | None = None
        self.hb_count = 0
        self.pairs = TickPairs()  # the recorder's pairing and loss count
        self._had_live = False
        self.clients: dict[str, Client] = {}
        self._next_client = 0
        self.arm_requested = False
        self.feeding = False
        self._keepalive = self.link.keepalive  # the link's one keepalive, at the dashboard's cadence
        self._keepalive.fastest = KEEPALIVE_S
        self.events: collections.deque[dict[str, Any]] = collections.deque(maxlen=200)
        # the commands go through the board library of `upright board` (arming token, refusals
        # as BoardError), on the shared link
        self.board = Board(self.link, port=str(self.info.get("port", "")), timeout=0.25, retries=3,
                           feed=False)  # the hub keeps the keepalive (KEEPALIVE_S, only for a live page)
        self._cmd_lock = threading.Lock()
        # recording
        self._rec_fh: Any = None
        self._rec_writer: Any = None
        self.rec_path: Path | None = None
        self.rec_rows = 0
        self.rec_lost_at_start = 0
        # measurements (server side and reported by the pages)
        self.rx_times: collections.deque[float] = collections.deque(maxlen=2000)
        self.push_ms: collections.deque[float] = collections.deque(maxlen=4000)
        self.page_latency_ms: collections.deque[float] = collections.deque(maxlen=4000)
        self.page_updates: collections.deque[float] = collections.deque(maxlen=4000)
        self._square: threading.Event | None = None
        self.stopping = threading.Event()
        self._policy = threading.Thread(target=self._policy_loop, name="dashboard-policy", daemon=True)
        self._policy.start()

    # ------------------------------------------------------------------ messages (pump thread)
    def on_message(self, m: M.Message, seq: int | None, t_rx: float | None = None) -> None:
        """Take one received message (the pump's thread); ``t_rx`` = epoch seconds it arrived."""
        t_rx = time.time() if t_rx is None else t_rx
        t = type(m)
        if t is _ACT:
            return
        if t in _PERIODIC:
            numbered = seq is not None and not (t is _HB and self.link.is_reply(seq))
            pair = self.pairs.add(m, seq if numbered else None, t_rx)
            if pair is not None:
                self._row(pair[0], pair[1], t_rx, seq)
        if t is _HB:
            hb = {"state": m.state, "faults": m.faults, "boot": m.boot, "uptime_ms": m.uptime_ms}
            changed = self.heartbeat is None or (hb["state"], hb["faults"]) != (self.heartbeat["state"], self.heartbeat["faults"])
            self.heartbeat = hb
            self.hb_count += 1
            # the heartbeat carries the low 8 bits of the active table's CRC-16 (VERSION has all 16):
            # a table known here whose low byte matches stays; another low byte means the board runs
            # a table this dashboard did not upload
            low = m.gains_crc
            known = self.gains.get("crc")
            if (known is None or (known & 0xFF) != low) and self.gains.get("crc_low8") != low:
                up = self.gains.get("uploaded_crc")
                if up is not None and (up & 0xFF) == low:
                    self.gains = {**self.gains, "crc": up, "crc_low8": low,
                                  "label": self.gains.get("uploaded_label", self.gains.get("label", ""))}
                else:
                    self.gains = {"crc": None, "crc_low8": low, "uploaded_crc": up,
                                  "uploaded_label": self.gains.get("uploaded_label"),
                                  "label": f"reported by the board (CRC low byte {low:#04x})"}
                self._broadcast(_event("gains", self.gains))
            if changed:
                self._broadcast(_event("hb", self._hb_payload()))
        if t is not _TS and t is not _TC:
            self.link.deliver(m, seq)

    @property
    def half_pairs(self) -> int:
        """Halves of a tick whose other half did not come (:class:`~host.hil.accounting.TickPairs`)."""
        return self.pairs.unpaired

    @property
    def lost(self) -> int:
        """Periodic frames missing by the board's sequence number (telemetry pairs and heartbeats
        share its counter; :class:`~host.hil.accounting.SeqAccount`)."""
        return self.pairs.seqs.lost

    def _row(self, s: M.Message, c: M.Message, t_rx: float, seq: int | None) -> None:
        hb = self.heartbeat or {"state": -1, "faults": 0}
        row = [self.n, round(t_rx - self.t0_wall, 4), *telemetry_values(s, c, hb["state"], hb["faults"]),
               -1 if seq is None else seq]
        row = [round(v, 6) if isinstance(v, float) else v for v in row]
        self.n += 1
        with self._lock:
            self.rows.append(row)
            self.rx_times.append(time.monotonic())
            if self._rec_writer is not None:
                self._rec_writer.writerow(row)
                self.rec_rows += 1
            self._broadcast(_event("t", {"r": row, "rx": round(t_rx * 1000.0, 3)}), t_rx)

    def _broadcast(self, event: str, t_rx: float | None = None) -> None:
        for c in list(self.clients.values()):
            if c.open:
                c.push(event, t_rx)

    def pushed(self, t_rx: float) -> None:
        """A row received at ``t_rx`` (epoch s) was written to a page's stream now."""
        self.push_ms.append((time.time() - t_rx) * 1000.0)

    def _hb_payload(self) -> dict[str, Any]:
        hb = self.heartbeat or {}
        st = hb.get("state")
        return {**hb, "state_name": M.STATES.get(st, "unknown") if st is not None else "no heartbeat yet",
                "fault_names": fault_names(hb.get("faults", 0))}

    # ------------------------------------------------------------------ pages
    def connect(self) -> Client:
        """A page opened its event stream."""
        with self._lock:  # hello, then the last rows, then live rows: in that order, none twice
            self._next_client += 1
            c = Client(f"p{self._next_client}-{int(time.time() * 1000) % 100000}")
            c.push(_event("hello", self.hello(c.id)))
            for row in list(self.rows)[-500:]:
                c.push(_event("t", {"r": row, "rx": None}))
            self.clients[c.id] = c
        return c

    def disconnect(self, c: Client) -> None:
        """A page's event stream closed."""
        c.open = False
        with self._lock:
            self.clients.pop(c.id, None)
        self._check_pages()

    def ping(self, cid: str, report: dict[str, Any] | None = None) -> bool:
        """A page is alive; ``report``: its ``latency_ms`` samples and ``updates`` (epoch ms of the
        screen updates since its last ping).  False for an unknown page."""
        c = self.clients.get(cid)
        if c is None or not c.open:
            return False
        c.last_ping = time.monotonic()
        if report:
            for v in report.get("latency_ms", [])[:500]:
                if isinstance(v, (int, float)) and math.isfinite(v):
                    self.page_latency_ms.append(float(v))
            for v in report.get("updates", [])[:500]:
                if isinstance(v, (int, float)) and math.isfinite(v):
                    self.page_updates.append(float(v) / 1000.0)
        return True

    def live_pages(self) -> list[str]:
        now = time.monotonic()
        return [c.id for c in list(self.clients.values()) if c.open and now - c.last_ping < PAGE_TIMEOUT_S]

    def _check_pages(self) -> None:
        # on the step from some live page to none: stop feeding, disarm
        if self.live_pages():
            self._had_live = True
            self.feeding = self.arm_requested
            return
        if not self._had_live and not self.arm_requested:
            return
        self._had_live = False
        was = self.feeding or self.arm_requested
        self.feeding = False
        self.arm_requested = False
        self._stop_square()
        hb = self.heartbeat or {}
        if was or hb.get("state") in _ARMED_STATES:
            self.note("last page closed: host heartbeat stopped, board disarmed")
            threading.Thread(target=self._safe, args=(self.disarm_now,), daemon=True).start()

    def _policy_loop(self) -> None:
        while not self.stopping.wait(0.05):
            self._check_pages()

    def _safe(self, fn: Callable[[], Any]) -> None:
        try:
            fn()
        except (LinkError, OSError, BoardError) as exc:
            self.note(f"disarm failed: {exc}")

    def tick_keepalive(self, now: float | None = None) -> None:
        """Send the host heartbeat if it is due (the pump's thread calls this)."""
        if self.keepalive and self.feeding:
            try:
                self._keepalive.tick(now)
            except LinkError as exc:
                self.note(f"host heartbeat failed: {exc}")

    @property
    def keepalives(self) -> int:
        """Host heartbeats sent."""
        return self._keepalive.sent

    def note(self, text: str) -> None:
        """An event line for the pages (and the console)."""
        ev = {"t": round(time.time() - self.t0_wall, 3), "text": text}
        self.events.append(ev)
        self._broadcast(_event("note", ev))

    # ------------------------------------------------------------------ commands (any thread)
    def _command(self, fn: Callable[[Link], Any], *, refresh: bool = False) -> Any:
        with self._cmd_lock:
            self.link.discard()
            try:
                return fn(self.link)
            finally:
                if refresh:  # a heartbeat now: the pages see the new state at once
                    try:
                        self.link.send(_REQUEST(msg_id=T.HEARTBEAT))
                    except LinkError:
                        pass

    def arm(self, cid: str) -> None:
        """Arm on behalf of a live page (the host heartbeat starts first).

        Raises
        ------
        PermissionError
            ``cid`` is not a live page.
        """
        if cid not in self.live_pages():
            raise PermissionError("arm needs a live dashboard page (its event stream open and pinging)")
        self.arm_requested = True
        self.feeding = True
        self.tick_keepalive()
        try:
            self._command(lambda L: self.board.arm(), refresh=True)
        except BaseException:
            self.arm_requested = False
            self.feeding = False
            raise
        self.note(f"armed (page {cid})")

    def disarm_now(self) -> None:
        self.arm_requested = False
        self.feeding = False
        self._stop_square()
        self._command(lambda L: self.board.disarm(), refresh=True)

    def disarm(self, cid: str = "") -> None:
        self.disarm_now()
        self.note("disarmed" + (f" (page {cid})" if cid else ""))

    def clear(self) -> None:
        self._command(lambda L: self.board.clear_faults(), refresh=True)
        self.note("faults cleared")

    def set_reference(self, x: float, *, stop_square: bool = True) -> None:
        if not math.isfinite(x):
            raise ValueError(f"reference must be finite, got {x!r}")
        if stop_square:
            self._stop_square()
        self._command(lambda L: self.board.set_reference(float(x)))

    def square(self, amplitude: float, period: float, low: float = 0.0) -> None:
        """Square wave on the reference: ``low`` and ``low + amplitude``, each for ``period / 2``
        (until :meth:`stop_square`, a reference step, a disarm or the last page closing)."""
        if not (math.isfinite(amplitude) and math.isfinite(low) and math.isfinite(period)):
            raise ValueError("square wave: amplitude, period and low must be finite")
        if not 0.2 <= period <= 60.0:
            raise ValueError(f"square wave period must be in 0.2..60 s, got {period!r}")
        self._stop_square()
        stop = threading.Event()
        self._square = stop

        def run() -> None:
            high = True
            while not stop.is_set() and not self.stopping.is_set():
                try:
                    self.set_reference(low + amplitude if high else low, stop_square=False)
                except (LinkError, OSError, BoardError) as exc:
                    self.note(f"square wave stopped: {exc}")
                    return
                high = not high
                stop.wait(period / 2.0)

        threading.Thread(target=run, name="dashboard-square", daemon=True).start()
        self.note(f"square wave {low:g} <-> {low + amplitude:g} m, period {period:g} s")

    def _stop_square(self) -> None:
        if self._square is not None:
            self._square.set()
            self._square = None

    def stop_square(self) -> None:
        self._stop_square()

    def upload_gains(self, blob: bytes, label: str) -> int:
        """Upload a gain table (refused by the board while armed); returns its CRC."""
        crc = M.crc16(blob)
        self._command(lambda L: L.upload_gains(blob, timeout=0.5, retries=3))
        self.gains = {"crc": crc, "label": label, "bytes": len(blob), "uploaded_crc": crc, "uploaded_label": label}
        self.note(f"gain table uploaded: {label}, CRC {crc:#06x}")
        self._broadcast(_event("gains", self.gains))
        return crc

    def param(self, name: str) -> int:
        return int(self._command(lambda L: L.param_get(name, timeout=0.25, retries=3)))

    # ------------------------------------------------------------------ recording
    def record_start(self) -> Path:
        with self._lock:
            if self._rec_writer is not None:
                return self.rec_path  # type: ignore[return-value]
            self.record_dir.mkdir(parents=True, exist_ok=True)
            path = self.record_dir / time.strftime("dashboard-%Y%m%d-%H%M%S.csv")
            k = 1
            while path.exists():
                path = self.record_dir / time.strftime(f"dashboard-%Y%m%d-%H%M%S-{k}.csv")
                k += 1
            self._rec_fh = open(path, "w", newline="")
            self._rec_writer = csv.writer(self._rec_fh)
            self._rec_writer.writerow(COLUMNS)
            self.rec_path = path
            self.rec_rows = 0
            self.rec_lost_at_start = self.pairs.lost
        self.note(f"recording to {path}")
        return path

    def record_stop(self) -> dict[str, Any]:
        with self._lock:
            if self._rec_fh is not None:
                self._rec_fh.close()
            self._rec_fh = None
            self._rec_writer = None
        st = self.record_status()
        if self.rec_path is not None:
            self.note(f"recording stopped: {self.rec_rows} rows in {self.rec_path}")
        return st

    def record_status(self) -> dict[str, Any]:
        return {"recording": self._rec_writer is not None, "path": str(self.rec_path) if self.rec_path else None,
                "rows": self.rec_rows, "lost": self.pairs.lost - self.rec_lost_at_start}

    def record_bytes(self) -> bytes | None:
        with self._lock:
            if self._rec_fh is not None:
                self._rec_fh.flush()
            if self.rec_path is None or not self.rec_path.exists():
                return None
            return self.rec_path.read_bytes()

    # ------------------------------------------------------------------ figures
    def hello(self, cid: str) -> dict[str, Any]:
        return {"id": cid, "info": self.info, "columns": COLUMNS, "gains": self.gains,
                "states": {str(k): v for k, v in M.STATES.items()},
                "faults": [[b, n, d] for b, (n, d) in fault_table().items()],
                "heartbeat": self._hb_payload(), "virtual": self.virtual is not None,
                "t0_wall_ms": self.t0_wall * 1000.0, "record": self.record_status(),
                "notes": list(self.events)[-20:]}

    def status(self) -> dict[str, Any]:
        link = self.link
        return {"info": self.info, "heartbeat": self._hb_payload(), "heartbeats": self.hb_count,
                "telemetry_rows": self.n, "telemetry_lost": self.pairs.lost,
                "link": {"sent": link.sent, "received": link.received, "drops": link.drops},
                "pages": len(self.clients), "live_pages": len(self.live_pages()),
                "arm_requested": self.arm_requested, "feeding": self.feeding, "keepalives": self.keepalives,
                "gains": self.gains, "record": self.record_status(), "stats": self.stats(),
                "notes": [e["text"] for e in list(self.events)[-10:]],
                "virtual": self.virtual.status() if self.virtual is not None else None}

    def stats(self) -> dict[str, Any]:
        """Measured rates and latencies (last ~2000 samples)."""
        def rate(ts: list[float]) -> float | None:
            return (len(ts) - 1) / (ts[-1] - ts[0]) if len(ts) > 2 and ts[-1] > ts[0] else None

        def pct(vs: list[float]) -> dict[str, Any]:
            if not vs:
                return {"n": 0}
            s = sorted(vs)
            q = lambda p: s[min(len(s) - 1, int(p * (len(s) - 1) + 0.5))]  # noqa: E731
            return {"n": len(s), "p50": round(q(0.5), 2), "p95": round(q(0.95), 2), "p99": round(q(0.99), 2),
                    "max": round(s[-1], 2), "mean": round(sum(s) / len(s), 2)}

        now = time.monotonic()
        rx = [t for t in list(self.rx_times) if now - t < 10.0]
        upd = sorted(self.page_updates)
        upd = [t for t in upd if time.time() - t < 10.0]
        return {"telemetry_hz": rate(rx), "page_updates_hz": rate(upd),
                "page_latency_ms": pct(list(self.page_latency_ms)), "server_push_ms": pct(list(self.push_ms))}

    def close(self) -> None:
        """Stop the policy thread and the square wave, close the recording (the link is the caller's)."""
        self.stopping.set()
        self._stop_square()
        self.record_stop()
        self.link.unshare()


class PlainPump:
    """The receive loop for a board on a port (real or emulated): every message to the hub,
    the host heartbeat while the hub feeds."""

    def __init__(self, hub: Hub) -> None:
        self.hub = hub
        self.error: str | None = None
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="dashboard-pump", daemon=True)

    def start(self) -> "PlainPump":
        self.thread.start()
        return self

    def _run(self) -> None:
        hub, link = self.hub, self.hub.link
        link.share(threading.current_thread())  # this thread reads; commands wait for what the hub delivers
        try:
            while not self._stop.is_set():
                m = link.recv(0.02)
                if m is not None:
                    hub.on_message(m, link.last_seq, time.time())
                hub.tick_keepalive()
        except LinkError as exc:
            if not self._stop.is_set():
                self.error = f"link failed: {exc}"
                hub.note(self.error)

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(timeout=2.0)
