"""A board on a link, operated from the host: identity, status, arming, parameters, gains.

One :class:`Board` wraps an open :class:`host.link.clients.Link` (serial or CAN; a real board,
the emulated Pico of ``upright emulate rp2040 --pty`` or the virtual board of
:mod:`host.boards.vport` -- the same code).  It learns what the firmware offers from the one
message table (:mod:`firmware.msgtable`), the one this checkout's firmware speaks (a board with
another table is refused by its hash): no branch here for a table without a message.

Every failure is a :class:`BoardError` (one line, exit status 1 in the CLI) or, for a bad
parameter name or value, a :class:`ParamInputError` (exit status 2).

Example
-------
>>> with Board.open("/dev/ttyUSB0") as b:             # doctest: +SKIP
...     print(b.status()["state"])
...     b.param_set("max_duty", 8000)
"""

from __future__ import annotations

import collections
import time
from pathlib import Path
from typing import Any, Callable, Iterable

from firmware import msgtable as T
from host.link import messages as M
from host.link import identity as I  # noqa: N812
from host.link.clients import CommandRefused, Link, LinkError, LinkTimeout, open_link

__all__ = [
    "BoardError", "NotSupported", "ParamInputError", "IdentityMismatch",
    "Board", "fault_table", "fault_names", "param_table", "param_info", "param_read_only", "check_param",
    "periodic_kinds", "gains_blob_from_file", "gains_blob_from_design",
]


class BoardError(RuntimeError):
    """The board could not be operated (no answer, refused, link lost): one line."""


class NotSupported(BoardError):
    """The firmware on the board (or this message table) has no such command."""


class IdentityMismatch(BoardError):
    """The board speaks another message table than this host."""


class ParamInputError(ValueError):
    """A parameter name or value that the parameter table refuses (before anything is sent)."""


# ------------------------------------------------------------------ tables
def fault_table() -> dict[int, tuple[str, str]]:
    """Fault bit -> ``(name, doc)``: ``firmware.msgtable.FAULTS``, the one fault table (the
    supervisor's ``F_*`` constants agree with it: ``tests/test_firmware_supervisor.py``)."""
    return {int(bit): (str(name), str(doc)) for bit, name, doc in sorted(T.FAULTS)}


def fault_names(flags: int) -> list[str]:
    """Names of the fault bits set in ``flags`` (unknown bits as ``bit<N>``)."""
    table = fault_table()
    names = []
    bit = 1
    while flags >= bit:
        if flags & bit:
            names.append(table[bit][0] if bit in table else f"bit{bit.bit_length() - 1}")
        bit <<= 1
    return names


def param_table() -> dict[str, dict[str, Any]]:
    """Parameter name -> ``index, unit, min, max, default, doc`` (``firmware.msgtable.PARAMS``)."""
    return {p[1]: {"index": p[0], "unit": p[2], "min": p[3], "max": p[4], "default": p[5], "doc": p[6]}
            for p in T.PARAMS}


def param_info(name: str) -> dict[str, Any]:
    """One parameter's row.

    Raises
    ------
    ParamInputError
        Unknown name (the message lists the known ones).
    """
    table = param_table()
    if name not in table:
        raise ParamInputError(f"unknown parameter {name!r}; known: {', '.join(table)}")
    return table[name]


def param_read_only(name: str) -> str | None:
    """Why a parameter cannot be written, from its row of the table (a doc that starts with
    ``read-only``), or ``None`` when it can.

    Raises
    ------
    ParamInputError
        Unknown name.
    """
    doc = param_info(name)["doc"].strip()
    if not doc.lower().startswith("read-only"):
        return None
    why = doc[len("read-only"):].lstrip(" :;,-")
    return why.split("(")[0].strip().rstrip(";,.") or "the board refuses writes"


def check_param(name: str, value: Any) -> int:
    """``value`` as the parameter's integer, checked against its range (and refused for a
    read-only parameter).

    Raises
    ------
    ParamInputError
        Unknown name, read-only, not an integer, or outside ``min..max``.
    """
    ro = param_read_only(name)
    if ro is not None:
        raise ParamInputError(f"{name} is read-only: {ro}")
    p = param_info(name)
    try:
        f = float(value)
        v = int(f)
        if v != f:
            raise ValueError
    except (TypeError, ValueError, OverflowError):
        raise ParamInputError(f"{name}: expected an integer in {p['unit'] or 'counts'}, got {value!r}") from None
    if not p["min"] <= v <= p["max"]:
        u = f" {p['unit']}" if p["unit"] else ""
        raise ParamInputError(f"{name}: {v}{u} outside {p['min']}..{p['max']}{u}")
    return v


def periodic_kinds() -> tuple[str, ...]:
    """Messages the board's pacer numbers with its own sequence counter (lost ones are counted)."""
    return ("heartbeat", "telem_state")


# ------------------------------------------------------------------ gain tables
def gains_blob_from_file(path: str | Path) -> bytes:
    """A gain table from a file: the raw upload bytes (``.bin``) or a gain module (``.py``,
    ``upright export --out FILE``; its ``FLAT`` list as little-endian int32).

    A ``.py`` file is read as data -- its ``FLAT = (...)`` assignment parsed with
    :func:`ast.literal_eval` -- and never executed.

    Raises
    ------
    ParamInputError
        Missing/unreadable file, or a module without a ``FLAT`` list of ints.
    """
    import struct

    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise ParamInputError(f"gain table {str(path)!r}: {exc.strerror or exc}") from None
    if p.suffix != ".py":
        if not data or len(data) % 4 or len(data) > T.GAINS_MAX:
            raise ParamInputError(f"gain table {str(path)!r}: {len(data)} bytes; expected a multiple of 4 "
                                  f"in 4..{T.GAINS_MAX} (int32 little-endian), or a .py gain module")
        return data
    flat = _flat_of_module(data, str(path))
    return struct.pack(f"<{len(flat)}i", *flat)


def _flat_of_module(data: bytes, name: str) -> list[int]:
    # a gain module is data: its FLAT assignment is read with ast.literal_eval, never run
    import ast

    try:
        tree = ast.parse(data.decode(), filename=name)
    except (SyntaxError, ValueError, UnicodeDecodeError) as exc:
        where = f" line {exc.lineno}" if getattr(exc, "lineno", None) else ""
        raise ParamInputError(f"gain table {name!r}: not a gain module ({type(exc).__name__}{where}: "
                              f"{getattr(exc, 'msg', exc)})") from None
    value: Any = None
    for node in tree.body:
        if (isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name)
                and node.targets[0].id == "FLAT"):
            expr = node.value
            if isinstance(expr, ast.Call) and isinstance(expr.func, ast.Name) and expr.func.id == "const" \
                    and len(expr.args) == 1:
                expr = expr.args[0]
            try:
                value = ast.literal_eval(expr)
            except (ValueError, TypeError, SyntaxError, MemoryError, RecursionError):
                raise ParamInputError(f"gain table {name!r} line {node.lineno}: FLAT is not a literal list of "
                                      "ints (gain modules are read as data, not run)") from None
    if not isinstance(value, (list, tuple)) or not value or not all(type(v) is int for v in value):
        raise ParamInputError(f"gain table {name!r}: no FLAT list of ints (write one with `upright export --out`)")
    return list(value)


def gains_blob_from_design(params: str | Path | None = None) -> tuple[bytes, str]:
    """The shipped design's table for a robot (``params``: a robot TOML, default ``sim/robot.toml``)."""
    from host.design.export import export
    from sim.params import load_params

    fd = export(params=load_params(params) if params else None)
    return fd.blob(), f"design for {params or 'sim/robot.toml'}"


# ------------------------------------------------------------------ the board
_DRAIN_S = 0.05
"""Seconds :meth:`Board.poll` goes on draining queued messages past its deadline."""


class Board:
    """An open link to a board with the state the host keeps about it.

    Parameters
    ----------
    link : Link
        An open link (:func:`host.link.clients.open_link`, ``SerialLink``, ``CanLink``).
    port : str
        Name for messages.
    timeout, retries : float, int
        Per request.
    """

    def __init__(self, link: Link, *, port: str = "", timeout: float = 0.3, retries: int = 3,
                 feed: bool = True) -> None:
        self.link = link
        self.port = port or getattr(link, "url", "") or "board"
        self.timeout = float(timeout)
        self.retries = int(retries)
        self.heartbeat: Any = None
        self.hb_times: collections.deque[float] = collections.deque(maxlen=64)
        self.identity: dict[str, Any] = {}
        self.armed_by_us = False
        #: the link's one host heartbeat (beats in the board's time: :mod:`host.link.keepalive`)
        self._keepalive = link.keepalive
        self._closed = False
        self.listeners: list[Callable[[Any, int | None, float], None]] = []
        #: board seconds per wall second (:meth:`measure_speed`; 1 until measured)
        self.speed = 1.0
        self._first: tuple[int, float] | None = None
        self._clock_measured = False  # speed followed from the heartbeats once measure_speed ran
        self._feeder: Any = None
        #: feed the watchdog from a thread while armed (False: the owner keeps its own keepalive, as the dashboard's hub)
        self.feed = bool(feed)

    # ---- opening ----
    @classmethod
    def open(cls, port: str, *, link: str = "serial", baudrate: int | None = None, node: int = 1,
             can_interface: str = "slcan", timeout: float | None = None, retries: int = 3,
             answer_timeout: float = 10.0, check_identity: bool = True) -> "Board":
        """Open ``port``, wait for the board to answer and check who it is.

        ``timeout`` (s per request attempt): ``None`` measures the board's speed once it answers
        (:meth:`measure_speed`, half a second) and scales the full-speed 0.3 s by it
        (:func:`host.hil.answer_time.request_time`: an emulated board at 0.15x gets 2 s).

        Raises
        ------
        BoardError
            Port cannot be opened, no answer within ``answer_timeout`` s, or a board whose
            message table differs from this host's (:class:`IdentityMismatch`).
        """
        from host.hil.answer_time import REQUEST_S, request_time

        if baudrate is None:
            from firmware.board import UART_BAUD

            baudrate = int(UART_BAUD)
        spec = f"can:{can_interface}:{port}" if link == "can" else port
        try:
            lk = open_link(spec, node_id=node, baudrate=baudrate)
        except (LinkError, ValueError) as exc:
            raise BoardError(str(exc).splitlines()[0]) from exc
        b = cls(lk, port=port, timeout=REQUEST_S if timeout is None else timeout, retries=retries)
        try:
            b.connect(answer_timeout=answer_timeout, check_identity=check_identity)
            if timeout is None:
                b.timeout = request_time(b.measure_speed())
        except BaseException:
            b.close(disarm=False)
            raise
        return b

    def connect(self, *, answer_timeout: float = 3.0, check_identity: bool = True) -> dict[str, Any]:
        """Wait for a heartbeat (asking for one), then read the identity."""
        deadline = time.monotonic() + answer_timeout
        while True:
            try:
                hb = self.query("heartbeat", timeout=min(self.timeout, answer_timeout), retries=0)
                self._first = (int(hb.uptime_ms), time.monotonic())
                break
            except BoardError as exc:
                if not isinstance(exc.__cause__, LinkTimeout) or time.monotonic() >= deadline:
                    if isinstance(exc.__cause__, LinkTimeout):
                        raise BoardError(f"no answer from {self.port} within {answer_timeout:g} s: is the board "
                                         "powered, running the upright firmware, on this port and baud rate?") from None
                    raise
        return self.identify(check=check_identity)

    def identify(self, *, check: bool = True) -> dict[str, Any]:
        """Identity: firmware version, table hashes, gain CRC, reset cause (VERSION; what the
        heartbeat carries if the board does not answer it).

        Raises
        ------
        IdentityMismatch
            ``check`` and the board's message-table hash differs from this host's.
        """
        ident: dict[str, Any] = {"version_message": False,
                                 "host_table_hash": I.table_hash(), "host_param_hash": I.param_hash()}
        try:
            v = self.query("version")
        except (NotSupported, BoardError):
            v = None
        if v is not None:
            ident["version_message"] = True
            ident.update(v.physical())
            fw = ident["fw_version"]
            ident["fw_version_text"] = f"{fw >> 4}.{fw & 15}"
            rc = ident["reset_cause"]
            names = {r[0]: r[1] for r in T.RESET_CAUSES}
            ident["reset_cause_name"] = names.get(rc, str(rc))
        hb = self.heartbeat
        if hb is not None and "gains_crc" not in ident:
            ident["gains_crc_low8"] = hb.gains_crc
        if "table_hash" in ident and "host_table_hash" in ident:
            ident["table_match"] = ident["table_hash"] == ident["host_table_hash"]
            if check and not ident["table_match"]:
                raise IdentityMismatch(
                    f"{self.port}: board's message table hash {ident['table_hash']:#06x} differs from this host's "
                    f"{ident['host_table_hash']:#06x}: flash this checkout's firmware (make firmware && make flash)")
        self.identity = ident
        return ident

    # ---- the board's clock ----
    def measure_speed(self, wall_s: float = 0.5) -> float:
        """Measure :attr:`speed` (board seconds per wall second, at most 1) from two heartbeats
        ``wall_s`` apart (:func:`host.hil.answer_time.board_speed`, as ``upright hil --port``);
        the first is the one :meth:`connect` got, when there is one."""
        from host.hil.answer_time import board_speed
        from host.hil.errors import HilError

        first = self._first
        if first is None:
            hb = self.query("heartbeat")
            first = (int(hb.uptime_ms), time.monotonic())
        try:
            self.speed = board_speed(self.link, first, wall_s=wall_s, timeout=max(10.0, 10 * self.timeout))
        except HilError as exc:
            raise BoardError(f"{self.port}: {exc}") from None
        self._first = None
        self._keepalive.restart(self.speed)
        self._clock_measured = True
        return self.speed

    def _clock_seen(self) -> None:
        # the link showed its keepalive the heartbeat (Link._ingest): the speed it follows
        if self._clock_measured:
            self.speed = self._keepalive.clock.speed

    def wall(self, board_s: float) -> float:
        """Wall seconds in which the board lives ``board_s`` seconds at its measured :attr:`speed`."""
        from host.hil.answer_time import wall_time

        return wall_time(board_s, self.speed)

    # ---- receiving ----
    def _observe(self, msg: Any, seq: int | None, t: float) -> None:
        if msg.NAME == "heartbeat":
            self.heartbeat = msg
            self.hb_times.append(t)
            if seq is not None:  # a periodic one (a reply's time is the request's)
                self._clock_seen()
        for fn in self.listeners:
            fn(msg, seq, t)

    def _observe_before_reply(self) -> None:
        # the frames that arrived while a request waited for its answer are queued ahead of it: the
        # listeners (a recorder labelling rows with the latest heartbeat, an excitation's column that
        # starts at the board's ACK) see them before the reply and what the caller does next -- else
        # the board's telemetry of before an arm is recorded after the heartbeat that says balancing
        n, self.link.queued_before_reply = self.link.queued_before_reply, 0
        for _ in range(n):
            msg = self.link.recv(timeout=0)
            if msg is None:
                break
            self._observe(msg, self.link.last_seq, time.monotonic())

    def poll(self, timeout: float = 0.0) -> list[tuple[Any, int | None, float]]:
        """Every message that arrives within ``timeout`` s (at least what is already waiting).

        Raises
        ------
        BoardError
            The link failed (unplugged, closed).
        """
        out = []
        deadline = time.monotonic() + timeout
        try:
            while True:
                left = max(0.0, deadline - time.monotonic())
                msg = self.link.recv(timeout=left)
                if msg is None:
                    break
                t = time.monotonic()
                item = (msg, self.link.last_seq, t)
                self._observe(*item)
                out.append(item)
                if not left:
                    # drain what is queued, then return -- but only for _DRAIN_S past the deadline: a
                    # host slower than the board's stream (starved by the machine's load) would else
                    # drain forever and its caller's keepalive never run (the board's watchdog
                    # latched so); what stays queued is read on the next call
                    if t - deadline > _DRAIN_S:
                        break
                    continue
        except LinkError as exc:
            raise _link_error(self.port, exc) from exc
        return out

    # ---- requests ----
    def request(self, msg: Any, **kw: Any) -> Any:
        """:meth:`Link.request` with the board's timeouts; errors as :class:`BoardError`."""
        kw.setdefault("timeout", self.timeout)
        kw.setdefault("retries", self.retries)
        try:
            reply = self.link.request(msg, **kw)
            self._observe_before_reply()
            return reply
        except CommandRefused as exc:
            self._observe_before_reply()
            if exc.reason == T.R_NOT_SUPPORTED or exc.reason_name == "unknown":
                raise NotSupported(f"{self.port}: {exc}") from exc
            raise BoardError(f"{self.port}: {exc}") from exc
        except LinkTimeout as exc:
            raise BoardError(f"{self.port}: {exc}") from exc
        except LinkError as exc:
            raise _link_error(self.port, exc) from exc

    def query(self, kind: str, **kw: Any) -> Any:
        """Ask for one message now (heartbeat, telem_state, timing, version, stats_...)."""
        cls = M.message_class(kind)
        m = self.request(M.BY_NAME["request"](msg_id=cls.ID), reply=cls, **kw)
        # a reply carries the request's sequence number, not the board's periodic counter
        self._observe(m, None, time.monotonic())
        return m

    def send(self, msg: Any) -> None:
        """Send without waiting for an answer."""
        try:
            self.link.send(msg)
        except LinkError as exc:
            raise _link_error(self.port, exc) from exc

    # ---- the host heartbeat ----
    def keepalive(self) -> bool:
        """Feed the board's link watchdog (the link's :class:`host.link.keepalive.Keepalive`: the host
        heartbeat) if its period passed since the last feed.  Returns True if it was sent.

        The period is in the board's time (:func:`host.link.keepalive.keepalive_period` of the
        speed followed from its heartbeats): a board slower than real time is not flooded."""
        try:
            return self._keepalive.tick()
        except LinkError as exc:
            raise _link_error(self.port, exc) from exc

    def _feed(self, on: bool) -> None:
        # while this host has the board armed, a thread ticks the same keepalive: a request waiting
        # for its answer (the board's link budget can hold a frame for many ticks; the attempts scale
        # with the board's clock) must not starve the board's watchdog (seen: an EXCITE's ACK awaited
        # 1.3 s of wall, 190 ms of board time, the watchdog latched at 250)
        import threading

        if on and self._feeder is None and self.feed:
            stop = threading.Event()

            def run() -> None:
                while not stop.wait(0.01):
                    try:
                        self._keepalive.tick()
                    except (BoardError, LinkError, OSError, ValueError):
                        return

            t = threading.Thread(target=run, daemon=True, name="upright-board-keepalive")
            self._feeder = (t, stop)
            t.start()
        elif not on and self._feeder is not None:
            t, stop = self._feeder
            self._feeder = None
            stop.set()
            if t is not threading.current_thread():
                t.join(timeout=1.0)

    # ---- state ----
    def state(self, fresh: bool = True) -> dict[str, Any]:
        """The last heartbeat as names (``fresh``: ask for one first)."""
        if fresh or self.heartbeat is None:
            self.query("heartbeat")
        hb = self.heartbeat
        d = hb.physical()
        d["state_name"] = M.STATES.get(hb.state, str(hb.state))
        d["fault_names"] = fault_names(hb.faults)
        return d

    def heartbeat_rate(self) -> float | None:
        """Heartbeats per second seen recently (None with fewer than two)."""
        ts = list(self.hb_times)
        if len(ts) < 2 or ts[-1] <= ts[0]:
            return None
        return (len(ts) - 1) / (ts[-1] - ts[0])

    def stats(self) -> dict[str, Any]:
        """The board's own counters (STATS messages, where the firmware has them) and TIMING."""
        out: dict[str, Any] = {}
        try:
            out["decode"] = self.query("stats_decode").physical()
            for name in ("stats_frames", "stats_loop"):
                out[name.split("_", 1)[1]] = self.link.expect(name, timeout=self.timeout * 2).physical()
        except (BoardError, LinkError):
            pass
        try:
            out["timing"] = self.query("timing").physical()
        except BoardError:
            pass
        return out

    def status_values(self) -> dict[str, int]:
        """The board's read-only status figures (``msgtable.STATUS``: uptime in full, loop
        starts, the saved copy in force...), read as PARAM_GET(``STATUS_BASE`` + k) where the
        board answers them (the first it does not answer ends the list)."""
        out: dict[str, int] = {}
        for row in T.STATUS:
            k, name = row[0], row[1]
            try:
                out[name] = int(self.request(M.BY_NAME["param_get"](index=T.STATUS_BASE + k)).value)
            except BoardError:
                break
        return out

    def status(self, listen: float = 1.0) -> dict[str, Any]:
        """Everything ``upright board status`` shows, as one dict (JSON-ready).

        ``listen``: seconds of passive listening to measure the heartbeat rate.
        """
        self.poll(listen)
        st = self.state(fresh=self.heartbeat is None)
        ident = self.identity or self.identify(check=False)
        link = self.link
        return {
            "port": self.port,
            "identity": ident,
            "state": st["state_name"],
            "state_code": st["state"],
            "faults": st["faults"],
            "fault_names": st["fault_names"],
            "heartbeat": {k: v for k, v in st.items() if k not in ("state_name", "fault_names")},
            "heartbeat_hz": self.heartbeat_rate(),
            "link": {"sent": link.sent, "received": link.received, "drops": link.drops,
                     "joined_bytes": link.joined},
            "board_stats": self.stats(),
            "board_status": self.status_values(),
        }

    # ---- commands ----
    def arm(self) -> None:
        """Arm with the board's arming token (SESSION); once more with a fresh token if the
        first was stale (a disarm drew a new one in between)."""
        cls = M.BY_NAME["arm"]
        for attempt in range(2):
            token = int(self.query("session").token)
            try:
                self.request(cls(epoch=token))
                break
            except BoardError as exc:
                cause = exc.__cause__
                if attempt or not isinstance(cause, CommandRefused) or cause.reason_name != "stale_epoch":
                    raise
        self.armed_by_us = True
        self._keepalive.fed()
        self._feed(True)

    def disarm(self) -> None:
        """Disarm (always accepted)."""
        self.request(M.BY_NAME["disarm"]())
        self.armed_by_us = False
        self._feed(False)

    def clear_faults(self) -> None:
        """Clear latched faults (refused while armed)."""
        self.request(M.BY_NAME["clear_faults"]())

    def set_mode(self, mode: str) -> None:
        """What the board runs on its link (``firmware/main.py``, MODE): ``robot`` (the control
        loop, at boot), ``hil`` (lockstep HIL for ``upright hil --port``) or ``repl`` (the link
        closed, MicroPython's REPL back: mpremote on a USB link).  Refused while armed."""
        value = {"robot": T.MODE_ROBOT, "hil": T.MODE_HIL, "repl": T.MODE_REPL}[mode]
        self.request(M.BY_NAME["mode"](mode=value))

    def set_reference(self, x_m: float) -> None:
        """Cart position reference (m); feeds the watchdog."""
        self.request(M.BY_NAME["set_reference"].from_physical(x_um=x_m))
        self._keepalive.fed()

    def param_get(self, name: str) -> int:
        """A parameter by name (:class:`ParamInputError` for an unknown name)."""
        p = param_info(name)
        return self.request(M.BY_NAME["param_get"](index=p["index"])).value

    def param_set(self, name: str, value: Any) -> int:
        """Set a parameter by name after the table's range check; returns the value in force."""
        v = check_param(name, value)
        p = param_info(name)
        return self.request(M.BY_NAME["param_set"](index=p["index"], value=v)).value

    def params(self) -> dict[str, int]:
        """Every parameter's current value."""
        return {name: self.param_get(name) for name in param_table()}

    def save(self) -> str:
        """Persist the parameters and the active gain table on the board.

        Returns the command's name (``save_config``).

        Raises
        ------
        NotSupported
            The firmware refuses it as unknown.
        """
        cls = M.BY_NAME["save_config"]
        self.request(cls(), timeout=max(self.timeout, self.wall(1.0)))
        return cls.NAME

    def upload_gains(self, blob: bytes) -> dict[str, Any]:
        """Upload a gain table (only while the motor is off) and read its CRC back.

        Returns
        -------
        dict
            ``crc`` (of the bytes sent), ``board_crc`` (read back: VERSION's full CRC, or
            the heartbeat's low 8 bits as ``board_crc_low8``), ``verified`` (bool or None
            when the firmware reports no CRC).
        """
        crc = M.crc16(bytes(blob))
        try:
            self.link.upload_gains(blob, timeout=self.timeout, retries=self.retries)
        except CommandRefused as exc:
            raise BoardError(f"{self.port}: gain table refused: {exc}") from exc
        except LinkTimeout as exc:
            raise BoardError(f"{self.port}: {exc}") from exc
        except LinkError as exc:
            raise _link_error(self.port, exc) from exc
        out: dict[str, Any] = {"crc": crc, "nbytes": len(blob), "board_crc": None, "verified": None}
        ident = self.identify(check=False)
        if "gains_crc" in ident and ident.get("version_message"):
            out["board_crc"] = ident["gains_crc"]
            out["verified"] = ident["gains_crc"] == crc
        else:
            hb = self.query("heartbeat")
            out["board_crc_low8"] = hb.gains_crc
            out["verified"] = hb.gains_crc == crc & 0xFF
        if out["verified"] is False:
            raise BoardError(f"{self.port}: gain table CRC read back {out.get('board_crc', out.get('board_crc_low8'))!r} "
                             f"differs from the uploaded table's {crc:#06x}")
        return out

    def raw_sensors(self) -> dict[str, int]:
        """One raw reading: ADC counts, the 16-bit encoder counter (``sensors_raw`` message).

        Raises
        ------
        NotSupported
            The firmware cannot report its raw sensors.
        """
        return self.query("sensors_raw").physical()

    # ---- lifetime ----
    def safe_disarm(self) -> bool:
        """Disarm if the board can still be reached; True if it answered."""
        try:
            self.disarm()
            return True
        except (BoardError, LinkError, OSError):
            return False

    def close(self, disarm: bool | None = None) -> None:
        """Close the link; disarm first if this host armed the board (or ``disarm=True``)."""
        if self._closed:
            return
        if disarm or (disarm is None and self.armed_by_us):
            self.safe_disarm()
        self._closed = True
        self._feed(False)
        try:
            self.link.close()
        except (LinkError, OSError):
            pass

    def __enter__(self) -> "Board":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _link_error(port: str, exc: BaseException) -> BoardError:
    # the link's own identity check (host.link.clients.IncompatibleBoard) or a lost link
    if type(exc).__name__ == "IncompatibleBoard":
        return IdentityMismatch(f"{port}: {_one(exc)}")
    return BoardError(f"link to {port} lost: {_one(exc)}")


def _one(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def wait_state(board: Board, states: Iterable[str], timeout: float, keepalive: bool = True) -> str:
    """Poll heartbeats until the board is in one of ``states`` (or ``timeout`` s); returns the state."""
    want = set(states)
    deadline = time.monotonic() + timeout
    st = board.state(fresh=True)["state_name"]
    while st not in want and time.monotonic() < deadline:
        if keepalive:
            board.keepalive()
        board.poll(0.05)
        st = board.state(fresh=True)["state_name"]
    return st
