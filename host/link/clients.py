"""Host link clients: one :class:`Link` API over serial (pyserial) or CAN (python-can).

The base class owns the template method :meth:`Link.recv` and request/response with
timeouts and retries; transports implement ``_send(msg, seq)`` and
``_recv_internal(timeout)``.

Safety rules the base class keeps (``firmware/msgtable.py``, docs/protocol.md):

* identity: before the first command a link reads the board's VERSION and refuses
  (:class:`IncompatibleBoard`) a board whose message-table hash differs from its own;
* arming: :meth:`Link.arm` reads the board's arming epoch from its heartbeat and sends
  ARM with it; every retry carries the same epoch, so an arm that arrives after a later
  disarm (or fault) is refused by the board instead of re-arming it;
* liveness: only HOST_HEARTBEAT (and set-points) feed the board's link watchdog; a link
  that arms starts sending it (:meth:`Link.start_heartbeat`) and flags a board whose own
  heartbeat is missing for 3 periods (:attr:`Link.board_silent`).

Threads: :meth:`Link.send` may be called from any thread.  The receive side is one thread's:
the caller's, or, once the link is *shared* (:meth:`Link.share`: the dashboard's hub), one pump
thread's that reads every frame and hands on, with :meth:`Link.deliver`, what commands wait for;
:meth:`Link.recv` and every request (``arm``, ``param_get``, ``upload_gains``...) on any other
thread then wait for those delivered frames.  Board tools and the dashboard use this one link.

Backends are chosen by name from :data:`BACKENDS` and
imported lazily.  Every pyserial / python-can error is re-raised as a
:class:`LinkError` ``from`` the original.

Example
-------
>>> with SerialLink("loop://") as link:            # doctest: +SKIP
...     link.send(messages.ParamGet(index=0))
...     link.recv(timeout=0.1)
"""

from __future__ import annotations

import collections
import importlib
import os
import select
import struct
import threading
import time
from typing import Any, Callable

from firmware import msgtable as T
from firmware.board import UART_BAUD as _UART_BAUD
from host.link import identity as ID
from host.link import messages as M
from host.link.keepalive import HOST_HEARTBEAT_S, Keepalive

__all__ = [
    "LinkError",
    "LinkTimeout",
    "LinkClosed",
    "CommandRefused",
    "IncompatibleBoard",
    "PortBusy",
    "port_holders",
    "Keepalive",
    "Link",
    "SerialLink",
    "CanLink",
    "BACKENDS",
    "open_link",
    "BOARD_BAUD",
]

# the board's UART rate (firmware/board.py UART_BAUD): the default of every serial link
BOARD_BAUD = int(_UART_BAUD)


class LinkError(OSError):
    """The link failed (port, bus, or a transport error); the cause is chained."""


class LinkTimeout(LinkError, TimeoutError):
    """No (matching) reply within the timeout, after every retry."""


class LinkClosed(LinkError):
    """The link was used after :meth:`Link.close`."""


class CommandRefused(LinkError):
    """The board answered NACK: the command was refused and changed nothing.

    Attributes
    ----------
    msg_id : int
        Id of the refused message.
    reason : int
        Reason code (``firmware.msgtable.REASONS``).
    reason_name : str
        Its name, e.g. ``"out_of_range"``.
    """

    def __init__(self, msg_id: int, reason: int) -> None:
        self.msg_id = msg_id
        self.reason = reason
        self.reason_name = M.REASON_NAMES.get(reason, f"reason {reason}")
        cls = M.MESSAGES.get(msg_id)
        name = cls.NAME if cls else f"id {msg_id}"
        doc = M.REASONS.get(reason, ("", "unknown reason"))[1]
        super().__init__(f"{name} refused: {self.reason_name} ({doc})")


class IncompatibleBoard(LinkError):
    """The board speaks another protocol: its message-table hash differs from the host's.

    Attributes
    ----------
    version : Message or None
        The board's VERSION message (``None`` if it does not report one).
    """

    def __init__(self, text: str, version: M.Message | None = None) -> None:
        self.version = version
        super().__init__(text)


class PortBusy(LinkError):
    """Another process holds the serial port: ports are opened exclusively, one tool per port.

    Attributes
    ----------
    port : str
        The port as given.
    holders : list of (int, str)
        ``(pid, command line)`` of the processes found holding it (may be empty).
    """

    def __init__(self, port: str, holders: list[tuple[int, str]]) -> None:
        self.port = port
        self.holders = holders
        if holders:
            who = "; ".join(f"PID {pid} ({cmd})" for pid, cmd in holders)
            text = f"port busy: {port} is held by {who}"
        else:
            text = f"port busy: {port} is held exclusively by another process"
        super().__init__(text + " (not an upright tool serving the port's hub): stop it first")


def port_holders(path: str) -> list[tuple[int, str]]:
    """Processes holding the device ``path`` (:func:`host.link.porthub.port_holders`)."""
    from host.link.porthub import port_holders as holders

    return holders(path)


def _exclusive_ok(url: str) -> bool:
    # a device path (not a pyserial URL) that is not the pty multiplexer: every open of
    # /dev/ptmx is a new pty on the same inode, a lock there would serialise them all
    if "://" in url or not os.path.exists(url):
        return False
    return os.path.basename(os.path.realpath(url)) != "ptmx"


# reply class wanted by a request, by request message name (default: ACK)
_REPLY: dict[str, str] = {"param_get": "param_value", "param_set": "param_value"}
_HEARTBEAT = M.BY_NAME["heartbeat"]
_VERSION = M.BY_NAME["version"]
#: board heartbeats that may be missing before :attr:`Link.board_silent` is set
SILENT_PERIODS = 3

#: python-can's ``serial`` interface reads a frame in pieces, each with the port's own
#: timeout: once a frame has started, wait this long for the rest of it (a frame is 15
#: bytes; a short wait would cut a frame that is still arriving on a loaded host)
STREAM_FRAME_WAIT_S = 0.05


class Link:
    """Abstract link: typed messages in and out.

    Parameters
    ----------
    backlog : int
        Messages kept for :meth:`recv` while :meth:`request` waits for its reply.
    """

    def __init__(self, *, backlog: int = 10000, check_identity: bool = True) -> None:
        self._queue: collections.deque[tuple[M.Message, int | None]] = collections.deque(maxlen=backlog)
        self._seq = 0
        self._closed = False
        self.sent = 0
        self.received = 0
        # one writer at a time (the heartbeat thread writes too), one reader at a time
        self._tx_lock = threading.Lock()
        self._rx_lock = threading.Lock()
        #: read the board's VERSION before the first command and refuse another table
        self.check_identity = check_identity
        #: the board's VERSION once read (:meth:`identify`)
        self.version: M.Message | None = None
        #: monotonic time of the last board HEARTBEAT received, and the last one
        self.last_heartbeat_at: float | None = None
        self.last_heartbeat: M.Message | None = None
        #: True while the board's heartbeat has been missing for SILENT_PERIODS periods
        #: (checked while the host heartbeat runs); silences counts such events
        self.board_silent = False
        self.silences = 0
        #: called with the silence in seconds when :attr:`board_silent` becomes True
        self.on_silent: Callable[[float], None] | None = None
        #: the host heartbeat of this link, beating in the board's time: every tool sends it through
        #: this one object (:mod:`host.link.keepalive`); :meth:`_ingest` shows it every board heartbeat
        self.keepalive = Keepalive(self.send)
        self._hb_thread: threading.Thread | None = None
        self._hb_stop = threading.Event()
        self._board_period: float | None = None
        #: the hub this link serves its port's other tools on (:mod:`host.link.porthub`)
        self._hub: Any = None
        # shared (share()): the pump thread reads; other threads take what it delivers
        self._shared = False
        self._reader: threading.Thread | None = None
        self._inbox: collections.deque[tuple[M.Message, int | None]] = collections.deque(maxlen=backlog)
        self._inbox_cv = threading.Condition()
        self._inbox_seq: int | None = None
        self._last_seq: int | None = None
        #: messages queued ahead of the last reply :meth:`expect` / :meth:`request` returned: they
        #: arrived before it (the first ones :meth:`recv` returns), so a reader that must see the
        #: board's stream in order takes them before it looks at the reply (Board.request)
        self.queued_before_reply = 0
        # seq -> time of the requests sent while shared: their replies carry the request's seq,
        # not the board's periodic counter (is_reply)
        self._requests: dict[int, float] = {}

    # ---- transport hooks ----
    def _send(self, msg: M.Message, seq: int) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _recv_internal(self, timeout: float | None) -> list[tuple[M.Message, int | None]]:  # pragma: no cover
        """Wait at most ``timeout`` s for input; return the ``(message, seq)`` it completed.

        ``seq`` is ``None`` for framings without sequence numbers (CAN).
        """
        raise NotImplementedError

    def _close(self) -> None:  # pragma: no cover - abstract
        pass

    #: the heartbeat thread may poll the input when nobody reads (a transport whose
    #: non-blocking read can split a frame says no)
    _background_reads = True

    @property
    def drops(self) -> dict[str, int]:
        """Frames dropped by the receiver, by cause."""
        return {}

    @property
    def joined(self) -> int:
        """Bytes of a frame the port held when the link opened (its tail: not a drop)."""
        return 0

    # ---- sharing between threads ----
    def share(self, reader: threading.Thread | None = None) -> None:
        """Let one pump thread own the receive side from now on (idempotent).

        The pump reads with :meth:`recv` as any owner would and hands each frame that commands
        may wait for to :meth:`deliver`; :meth:`recv`, :meth:`expect` and :meth:`request` called
        on any other thread take delivered frames only.  ``reader``: the pump thread (it may
        say so later, ``share(threading.current_thread())`` from the pump itself).
        """
        self._shared = True
        if reader is not None:
            self._reader = reader

    def unshare(self) -> None:
        """Back to one owner for everything: the calling thread reads again; undelivered frames dropped."""
        self._shared = False
        self._reader = None
        self.discard()

    @property
    def shared(self) -> bool:
        """True while a pump owns the receive side (:meth:`share`)."""
        return self._shared

    def deliver(self, msg: M.Message, seq: int | None) -> None:
        """Hand one received frame to the threads that wait for replies (the pump's thread)."""
        with self._inbox_cv:
            self._inbox.append((msg, seq))
            self._inbox_cv.notify_all()

    def discard(self) -> None:
        """Forget the frames delivered so far (a command then matches only fresh replies)."""
        with self._inbox_cv:
            self._inbox.clear()

    def is_reply(self, seq: int) -> bool:
        """True if ``seq`` is that of a request sent in the last second while shared (then forgotten)."""
        t = self._requests.pop(seq, None)
        return t is not None and time.monotonic() - t < 1.0

    def _waits_for_pump(self) -> bool:
        return self._shared and threading.current_thread() is not self._reader

    def _take(self, timeout: float | None) -> None:
        # a thread that is not the pump: wait for a delivered frame (the inbox is its queue)
        with self._inbox_cv:
            if not self._inbox:
                self._inbox_cv.wait(timeout)

    def _side(self) -> tuple[collections.deque[tuple[M.Message, int | None]], Callable[[float | None], None]]:
        # the queue this thread reads and how it waits for more
        if self._waits_for_pump():
            return self._inbox, self._take
        return self._queue, self._pull

    @property
    def last_seq(self) -> int | None:
        """Serial sequence number of the last message this thread's :meth:`recv` / request took."""
        return self._inbox_seq if self._waits_for_pump() else self._last_seq

    @last_seq.setter
    def last_seq(self, seq: int | None) -> None:
        if self._waits_for_pump():
            self._inbox_seq = seq
        else:
            self._last_seq = seq

    # ---- public API ----
    def send(self, msg: M.Message, *, _tag: Any = None) -> int:
        """Send one message; return the sequence number used (serial framing).

        ``_tag``: the port hub's note of which attached tool sent the frame.

        Raises
        ------
        LinkError
        """
        if self._closed:
            raise LinkClosed("link is closed")
        if not isinstance(msg, M.Message):
            raise TypeError(f"expected a protocol message, got {type(msg).__name__}")
        with self._tx_lock:
            seq = self._seq
            self._seq = (seq + 1) & 0xFF
            hub = self._hub
            if hub is not None:
                hub.note_sent(msg, seq, _tag)
            if self._shared and msg.NAME == "request":
                now = time.monotonic()
                if len(self._requests) > 64:  # replies that never came: forget the stale ones
                    self._requests = {k: v for k, v in self._requests.items() if now - v < 1.0}
                self._requests[seq] = now
            self._send(msg, seq)
            self.sent += 1
        return seq

    def _pull(self, timeout: float | None) -> None:
        # read what arrives within timeout into the queue; note board heartbeats
        with self._rx_lock:
            got = self._recv_internal(timeout)
        self._ingest(got)

    def _ingest(self, got: list[tuple[M.Message, int | None]]) -> None:
        hub = self._hub
        if hub is not None and got:
            # answers to an attached tool's requests go to that tool, not into this queue
            got = hub.dispatch(got)
        for m, _ in got:
            if isinstance(m, _HEARTBEAT):
                self.last_heartbeat = m
                self.last_heartbeat_at = time.monotonic()
                self.board_silent = False
                self.keepalive.observe(m.uptime_ms, self.last_heartbeat_at)
        self.received += len(got)
        self._queue.extend(got)

    def recv(self, timeout: float | None = None) -> M.Message | None:
        """Next received message, or ``None`` when ``timeout`` s pass without one.

        ``timeout=None`` waits forever; ``0`` polls.  The serial sequence number of the
        returned message is in :attr:`last_seq` (``None`` on CAN).
        """
        if self._closed:
            raise LinkClosed("link is closed")
        q, pull = self._side()
        deadline = None if timeout is None else time.monotonic() + timeout
        while not q:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            pull(left)
            if not q and deadline is not None and time.monotonic() >= deadline:
                return None
        msg, self.last_seq = q.popleft()
        return msg

    def expect(self, kind: type[M.Message] | str, timeout: float = 1.0) -> M.Message:
        """Wait for a message of ``kind``; other messages stay queued for :meth:`recv`.

        Raises
        ------
        LinkTimeout
        """
        cls = M.message_class(kind) if isinstance(kind, str) else kind
        return self._wait(lambda m, seq: isinstance(m, cls), timeout, f"no {cls.NAME} within {timeout} s")

    def _wait(self, match: Any, timeout: float, what: str) -> M.Message:
        q, pull = self._side()
        deadline = time.monotonic() + timeout
        held: list[tuple[M.Message, int | None]] = []
        try:
            while True:
                while q:
                    item = q.popleft()
                    if match(*item):
                        self.last_seq = item[1]
                        self.queued_before_reply = len(held)
                        return item[0]
                    held.append(item)
                left = deadline - time.monotonic()
                if left <= 0:
                    raise LinkTimeout(what)
                pull(left)
        finally:
            q.extendleft(reversed(held))

    def request(self, msg: M.Message, *, reply: type[M.Message] | str | None = None,
                timeout: float = 0.25, retries: int = 3) -> M.Message:
        """Send ``msg`` and wait for its answer, resending on timeout.

        Parameters
        ----------
        msg : Message
            A board-bound message.
        reply : message class or name, optional
            What answers it (default ``ack``, ``param_value`` for parameter
            requests, the requested message for ``request``).
        timeout : float
            Seconds to wait per attempt.
        retries : int
            Resends after the first attempt.

        Returns
        -------
        Message
            The reply (``Ack``, ``ParamValue``, ...).

        Raises
        ------
        CommandRefused
            The board answered NACK for this message.
        LinkTimeout
            No answer after ``1 + retries`` attempts.
        IncompatibleBoard
            The board's message table is not the host's (checked once, before the first
            request; see :meth:`identify`).
        """
        if self.check_identity and self.version is None and not _is_version_request(msg):
            self.identify(timeout=timeout, retries=retries)
        if reply is None:
            if msg.NAME == "request":
                reply = M.MESSAGES[getattr(msg, "msg_id")]
            else:
                reply = _REPLY.get(msg.NAME, "ack")
        cls = M.message_class(reply) if isinstance(reply, str) else reply

        sent: set[int] = set()
        # what was already received when the request went out cannot answer it (a periodic
        # heartbeat whose seq happens to be the request's, or any one on CAN, is stale)
        before: set[int] = set()

        def match(m: M.Message, seq: int | None) -> bool:
            # replies carry the seq of the request they answer (serial); a late reply
            # to an earlier request stays queued for recv()
            if seq is not None and seq not in sent:
                return False
            if id(m) in before:
                return False
            if isinstance(m, M.BY_NAME["nack"]) and m.msg_id == msg.ID:
                return True
            if isinstance(m, M.BY_NAME["ack"]):
                return cls.NAME == "ack" and m.msg_id == msg.ID
            if cls.NAME == "param_value":
                return isinstance(m, cls) and m.index == getattr(msg, "index")
            return isinstance(m, cls)

        for attempt in range(retries + 1):
            before.update(id(m) for m, _ in list(self._side()[0]))
            sent.add(self.send(msg))
            try:
                m = self._wait(match, timeout, "")
            except LinkTimeout:
                continue
            if m.NAME == "nack":
                raise CommandRefused(m.msg_id, m.reason)
            return m
        raise LinkTimeout(f"no answer to {msg.NAME} after {retries + 1} attempts of {timeout} s")

    # ---- identity and liveness ----
    def identify(self, **kw: Any) -> M.Message:
        """Read the board's VERSION and check its message-table hash against the host's.

        Returns
        -------
        Message
            The board's VERSION (also kept in :attr:`version`).

        Raises
        ------
        IncompatibleBoard
            The board's table hash differs from the host's, or it does not report one.
        """
        try:
            v = self.request(M.BY_NAME["request"](msg_id=T.VERSION), reply=_VERSION, **kw)
        except CommandRefused as exc:
            raise IncompatibleBoard(f"the board does not report its protocol identity ({exc.reason_name}): "
                                    "its firmware is older than this host's protocol; flash matching firmware") from exc
        mine = ID.table_hash()
        if v.table_hash != mine:
            raise IncompatibleBoard(f"the board's message table (hash {v.table_hash:#06x}, firmware version "
                                    f"{v.fw_version >> 4}.{v.fw_version & 15}) differs from this host's "
                                    f"({mine:#06x}): refusing to operate it; flash matching firmware or use a "
                                    "matching host", v)
        self.version = v
        return v

    def start_heartbeat(self, period: float = HOST_HEARTBEAT_S, board_period: float | None = None) -> None:
        """Send HOST_HEARTBEAT from a thread until :meth:`close` / :meth:`stop_heartbeat`: every
        ``period`` s of wall time to a board at full speed, every
        :data:`~host.link.keepalive.KEEPALIVE_BOARD_S` of its clock to a slower one
        (:attr:`keepalive`).

        While it runs, a board heartbeat missing for :data:`SILENT_PERIODS` periods sets
        :attr:`board_silent` (and calls :attr:`on_silent`).  ``board_period``: the board's
        heartbeat period in s (default: its ``heartbeat_ms`` parameter, read now; 0 = no
        silence check).  Idempotent.
        """
        if self._hb_thread is not None:
            return
        if period <= 0:
            raise ValueError(f"period must be > 0, got {period!r}")
        if board_period is None:
            try:
                board_period = self.param_get("heartbeat_ms") / 1000.0
            except LinkError:
                board_period = 0.0
        self._board_period = board_period or None
        self.last_heartbeat_at = time.monotonic()
        self._hb_stop.clear()
        keep = self.keepalive
        keep.fastest = float(period)
        keep.beat()
        self._hb_thread = threading.Thread(target=self._heartbeat_loop, args=(keep,), daemon=True,
                                           name="upright-host-heartbeat")
        self._hb_thread.start()

    def stop_heartbeat(self) -> None:
        """Stop sending HOST_HEARTBEAT (the board's watchdog then faults an armed board)."""
        t = self._hb_thread
        if t is not None:
            self._hb_stop.set()
            if t is not threading.current_thread():
                t.join(timeout=2)
            self._hb_thread = None

    @property
    def heartbeat_running(self) -> bool:
        """True while :meth:`start_heartbeat`'s thread sends."""
        return self._hb_thread is not None

    def _heartbeat_loop(self, keep: Keepalive) -> None:
        while not self._hb_stop.wait(max(0.002, keep.due_in())):
            try:
                keep.tick()
                # nobody reading: take what arrived (board heartbeats) into the queue (never
                # while shared: the pump reads, and notes the board's heartbeats itself)
                if self._background_reads and not self._shared and self._rx_lock.acquire(blocking=False):
                    try:
                        got = self._recv_internal(0)
                    finally:
                        self._rx_lock.release()
                    self._ingest(got)
            except (LinkError, OSError, ValueError):
                return
            self._check_silence()

    def _check_silence(self) -> None:
        bp = self._board_period
        at = self.last_heartbeat_at
        if bp is None or at is None or self.board_silent:
            return
        age = time.monotonic() - at
        if age > SILENT_PERIODS * bp:
            self.board_silent = True
            self.silences += 1
            if self.on_silent is not None:
                self.on_silent(age)

    # ---- commands ----
    def arm(self, **kw: Any) -> None:
        """Arm the motor with the board's current arming token (refused while a fault is latched).

        Reads the token from a fresh SESSION, then sends ARM(token); retries resend the
        same token, so a late retry after a disarm (which draws a new token) is refused
        (``stale_epoch``) instead of re-arming.  Starts the host heartbeat
        (:meth:`start_heartbeat`) if it is not running: the board's watchdog needs it.
        """
        token = self.session_token(**kw)
        if not self.heartbeat_running:
            self.start_heartbeat()
        self.request(M.BY_NAME["arm"](epoch=token), **kw)

    def session_token(self, **kw: Any) -> int:
        """The board's current arming token (``session.token``), for ARM and GAINS_BEGIN."""
        return int(self.query("session", **kw).token)

    def disarm(self, **kw: Any) -> None:
        """Disarm the motor."""
        self.request(M.BY_NAME["disarm"](), **kw)

    def clear_faults(self, **kw: Any) -> None:
        """Clear latched faults."""
        self.request(M.BY_NAME["clear_faults"](), **kw)

    def set_reference(self, x_m: float, **kw: Any) -> None:
        """Set the cart position reference in metres."""
        self.request(M.BY_NAME["set_reference"].from_physical(x_um=x_m), **kw)

    def param_get(self, param: int | str, **kw: Any) -> int:
        """Read a parameter by index or name."""
        return self.request(M.BY_NAME["param_get"](index=_param_index(param)), **kw).value

    def param_set(self, param: int | str, value: int, **kw: Any) -> int:
        """Write a parameter; return the value now in force."""
        return self.request(M.BY_NAME["param_set"](index=_param_index(param), value=int(value)), **kw).value

    def query(self, kind: type[M.Message] | str, **kw: Any) -> M.Message:
        """Ask the board for one message now (heartbeat, telem_state, timing)."""
        cls = M.message_class(kind) if isinstance(kind, str) else kind
        return self.request(M.BY_NAME["request"](msg_id=cls.ID), reply=cls, **kw)

    def upload_gains(self, table: bytes, **kw: Any) -> None:
        """Upload a gain table in chunks and commit it (applied only while disarmed).

        Raises
        ------
        CommandRefused
            Bad length, CRC, shape, unstable table, or the board is armed.
        """
        table = bytes(table)
        if not 0 < len(table) <= T.GAINS_MAX:
            raise ValueError(f"gain table of {len(table)} bytes; must be 1..{T.GAINS_MAX}")
        token = self.session_token(**kw)  # the upload belongs to this session
        self.request(M.BY_NAME["gains_begin"](nbytes=len(table), crc=M.crc16(table), token=token), **kw)
        n = T.CHUNK_BYTES
        for off in range(0, len(table), n):
            data = table[off:off + n].ljust(n, b"\x00")
            self.request(M.BY_NAME["gains_chunk"](offset=off, data=data), **kw)
        self.request(M.BY_NAME["gains_commit"](check=M.table_check(table)), **kw)

    # ---- lifetime ----
    def close(self) -> None:
        """Release the port or bus (idempotent)."""
        if not self._closed:
            self.stop_heartbeat()
            hub, self._hub = self._hub, None
            if hub is not None:
                hub.close()
            self._closed = True
            with self._tx_lock:
                self._close()

    def __enter__(self) -> "Link":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _is_version_request(msg: M.Message) -> bool:
    return msg.NAME == "request" and getattr(msg, "msg_id") == T.VERSION


def _param_index(param: int | str) -> int:
    if isinstance(param, str):
        try:
            return M.PARAMS[param][0]
        except KeyError:
            raise ValueError(f"unknown parameter {param!r}; known: {', '.join(M.PARAMS)}") from None
    return int(param)


class SerialLink(Link):
    """Serial framing over pyserial (any ``serial_for_url`` URL: a device, ``loop://``, a pty).

    A device (a tty, a pty's slave) is opened exclusively (pyserial ``exclusive=True``, an
    ``flock`` on the device), and the link serves the device's other upright tools through a
    local hub (:mod:`host.link.porthub`): a second tool on the same port attaches to it
    (:attr:`via_hub`) instead of both reading half the frames; a port held by anything else
    is refused with :class:`PortBusy`, naming the process that holds it.

    Parameters
    ----------
    url : str
        Port or URL.
    baudrate : int
        Baud rate (ignored by ptys and USB CDC).
    backlog : int
        See :class:`Link`.
    hub : bool
        Serve (or attach to) the port's hub; False: exclusive only.

    """

    def __init__(self, url: str, baudrate: int = BOARD_BAUD, *, backlog: int = 10000,
                 check_identity: bool = True, hub: bool = True) -> None:
        super().__init__(backlog=backlog, check_identity=check_identity)
        import serial

        self._serial_mod = serial
        self.url = url
        self._baudrate = baudrate
        self._exclusive = _exclusive_ok(url)
        self._use_hub = bool(hub and self._exclusive and os.environ.get("UPRIGHT_PORT_HUB", "1") != "0")
        self._reopen_lock = threading.Lock()
        #: True when another tool holds the port and this link goes through its hub
        self.via_hub = False
        #: ``(pid, command)`` of the tool whose hub this link uses
        self.hub_owner: list[tuple[int, str]] = []
        #: times this link moved on after the tool whose hub it used left (to the port
        #: itself, or to the hub of the tool that took the port)
        self.rehomed = 0
        self.decoder = M.SerialStreamDecoder()
        self._ser: Any = None
        self._fd: int | None = None
        self._install(*self._open_port())

    def _open_port(self) -> tuple[Any, bool]:
        # (the port or the hub's socket, True for the hub)
        serial = self._serial_mod
        url = self.url
        kw: dict[str, Any] = {"exclusive": True} if self._exclusive else {}
        try:
            return serial.serial_for_url(url, baudrate=self._baudrate, timeout=0, **kw), False
        except (serial.SerialException, OSError, ValueError) as exc:
            if not (kw and "exclusively lock" in str(exc)):
                raise LinkError(f"cannot open serial port {url!r}: {exc}") from exc
            from host.link import porthub

            sp = porthub.attach(url) if self._use_hub else None
            if sp is None:
                raise PortBusy(url, port_holders(url)) from exc
            return sp, True

    def _install(self, ser: Any, via_hub: bool) -> None:
        self._ser = ser
        self.via_hub = via_hub
        self.hub_owner = port_holders(self.url) if via_hub else []
        # the port is joined mid-stream: the tail of a frame sent before it was opened (or cut by
        # the move to or from a hub) is not a drop; the counts go on
        dec = M.SerialStreamDecoder(mid_stream=True)
        dec.drops, dec.ok, dec.joined = self.decoder.drops, self.decoder.ok, self.decoder.joined
        self.decoder = dec
        # the port stays non-blocking (timeout 0): waiting is a select() on its file
        # descriptor when it has one (changing a pyserial timeout reconfigures the tty)
        try:
            self._fd = ser.fileno()
        except (AttributeError, OSError, ValueError, self._serial_mod.SerialException):
            self._fd = None
        if self._use_hub and not via_hub:
            from host.link import porthub

            try:
                self._hub = porthub.PortHub(self, self.url)
            except OSError:
                self._hub = None  # no hub: the port is exclusive all the same

    def _reopen(self, dead: Any, why: BaseException) -> None:
        # the tool whose hub this link used has left: take the port, or attach to the hub
        # of the tool that took it (a few seconds at most; the old owner's lock goes with it)
        with self._reopen_lock:
            if self._ser is not dead or self._closed:
                return
            try:
                dead.close()
            except OSError:
                pass
            deadline = time.monotonic() + 3.0
            while True:
                try:
                    self._install(*self._open_port())
                    self.rehomed += 1
                    return
                except PortBusy as exc:
                    if time.monotonic() > deadline:
                        raise LinkError(f"{self.url}: the tool whose hub this link used has left ({why}), and {exc}") \
                            from exc
                time.sleep(0.05)

    @property
    def drops(self) -> dict[str, int]:
        return dict(self.decoder.drops)

    @property
    def joined(self) -> int:
        return self.decoder.joined

    def _send(self, msg: M.Message, seq: int) -> None:
        data = M.encode_serial(msg, seq)
        for attempt in range(2):
            ser = self._ser
            try:
                ser.write(data)
                ser.flush()
                return
            except (self._serial_mod.SerialException, OSError) as exc:
                if not self.via_hub or attempt:
                    raise LinkError(f"write to {self.url!r} failed: {exc}") from exc
                self._reopen(ser, exc)

    def _recv_internal(self, timeout: float | None) -> list[tuple[M.Message, int | None]]:
        ser = self._ser
        try:
            n = ser.in_waiting
            if n:
                data = ser.read(n)
            elif timeout == 0:
                return []
            elif self._fd is not None:
                if not select.select([self._fd], [], [], timeout)[0]:
                    return []
                data = ser.read(max(1, ser.in_waiting))
            else:
                if ser.timeout != timeout:
                    ser.timeout = timeout
                data = ser.read(1)
                n = ser.in_waiting
                if n:
                    data += ser.read(n)
                ser.timeout = 0
        except (self._serial_mod.SerialException, OSError, ValueError) as exc:
            if self.via_hub and not self._closed:
                self._reopen(ser, exc)
                return []
            raise LinkError(f"read from {self.url!r} failed: {exc}") from exc
        return list(self.decoder.feed(data))

    def write_raw(self, data: bytes) -> None:
        """Write raw bytes (tests and fault injection)."""
        self._ser.write(data)

    def _close(self) -> None:
        self._ser.close()


class CanLink(Link):
    """CAN framing over any python-can bus.

    Parameters
    ----------
    bus : can.BusABC, optional
        An open bus; otherwise one is created from ``bus_kwargs``
        (e.g. ``interface="virtual", channel="x"``).
    node_id : int
        The board's node id (0..63).
    backlog : int
        See :class:`Link`.
    stream_crc : bool, optional
        Frames travel as bytes on a stream (python-can's ``serial`` interface): send and
        check the CRC each frame carries in its timestamp field
        (:func:`host.link.messages.serial_can_crc`).  Default: True exactly for a
        ``serial``-interface bus.
    **bus_kwargs
        Passed to ``can.Bus`` when ``bus`` is not given.
    """

    def __init__(self, bus: Any = None, *, node_id: int = 1, backlog: int = 10000, check_identity: bool = True,
                 stream_crc: bool | None = None, **bus_kwargs: Any) -> None:
        super().__init__(backlog=backlog, check_identity=check_identity)
        import can

        self._can = can
        if not 0 <= node_id < 2**T.NODE_BITS:
            raise ValueError(f"node_id {node_id} outside 0..{2**T.NODE_BITS - 1}")
        self.node_id = node_id
        self._own_bus = bus is None
        if bus is None:
            try:
                bus = can.Bus(**bus_kwargs)
            except (can.CanError, OSError, ValueError, ImportError) as exc:
                raise LinkError(f"cannot open CAN bus {bus_kwargs}: {exc}") from exc
        elif bus_kwargs:
            raise TypeError(f"unexpected keyword arguments with an open bus: {sorted(bus_kwargs)}")
        self.bus = bus
        if stream_crc is None:
            stream_crc = type(bus).__module__.startswith("can.interfaces.serial")
        self.stream_crc = bool(stream_crc)
        # python-can's serial interface reads a frame in pieces with the port's timeout: a
        # poll that starts mid-frame would lose it, so only the reader polls
        self._background_reads = not self.stream_crc
        if self.stream_crc and getattr(bus, "_ser", None) is not None:
            # idle waits happen in _stream_readable (honouring recv's timeout); the port's
            # own timeout then only bounds the wait for the rest of a started frame
            bus._ser.timeout = STREAM_FRAME_WAIT_S
        self._drops = {"unknown": 0, "length": 0, "other": 0, "crc": 0, "framing": 0}

    @property
    def drops(self) -> dict[str, int]:
        return dict(self._drops)

    def _send(self, msg: M.Message, seq: int) -> None:
        cid, data = M.encode_can(msg, self.node_id)
        if self.stream_crc:
            # python-can's serial interface writes int(timestamp * 1000) as the u32 field
            ts = (M.serial_can_crc(cid, data) + 0.5) / 1000.0
            frame = self._can.Message(arbitration_id=cid, data=data, is_extended_id=False, timestamp=ts)
        else:
            frame = self._can.Message(arbitration_id=cid, data=data, is_extended_id=False)
        try:
            self.bus.send(frame)
        except (self._can.CanError, OSError, ValueError) as exc:
            raise LinkError(f"CAN send failed: {exc}") from exc

    def _stream_readable(self, timeout: float | None) -> bool:
        """Wait up to ``timeout`` for a byte on a stream bus's port (python-can's ``serial``).

        python-can's ``serial`` interface ignores ``recv``'s timeout and reads with the port's;
        waiting here first lets the port keep a timeout long enough for a whole frame.
        """
        ser = getattr(self.bus, "_ser", None)
        if ser is None:
            return True
        fileno = getattr(ser, "fileno", None)
        if fileno is None:
            return True  # a port without a file descriptor: python-can waits the port's timeout
        try:
            return bool(ser.in_waiting) or bool(select.select([fileno()], [], [], timeout)[0])
        except (OSError, ValueError) as exc:
            raise LinkError(f"CAN receive failed: {exc}") from exc

    def _recv_internal(self, timeout: float | None) -> list[tuple[M.Message, int | None]]:
        if self.stream_crc:
            if not self._stream_readable(timeout):
                return []
            timeout = 0.0
        try:
            frame = self.bus.recv(timeout)
        except (TypeError, struct.error):
            # python-can's serial interface on a frame cut short (a lossy line, or a frame
            # still arriving when the port's timeout ran out): struct.unpack or ord() of a
            # short read.  Dropped and counted; the interface resynchronises on 0xAA
            if not self.stream_crc:
                raise
            self._drops["framing"] += 1
            return []
        except ValueError:
            # a malformed frame the interface could not parse (python-can's serial
            # interface raises ValueError for a DLC > 8): dropped and counted, the
            # interface resynchronises on the next frame
            self._drops["length"] += 1
            return []
        except self._can.CanOperationError as exc:
            if self.stream_crc and "delimiter" in str(exc):
                # python-can's serial interface: a frame without its 0xBB end marker
                self._drops["framing"] += 1
                return []
            raise LinkError(f"CAN receive failed: {exc}") from exc
        except (self._can.CanError, OSError) as exc:
            raise LinkError(f"CAN receive failed: {exc}") from exc
        if frame is None:
            return []
        if frame.is_extended_id or frame.is_error_frame or frame.is_remote_frame:
            self._drops["other"] += 1
            return []
        node, mid = frame.arbitration_id >> T.MSG_BITS, frame.arbitration_id & T.MAX_ID
        if node != self.node_id:
            self._drops["other"] += 1
            return []
        if self.stream_crc and round(frame.timestamp * 1000) != M.serial_can_crc(frame.arbitration_id, bytes(frame.data)):
            self._drops["crc"] += 1
            return []
        try:
            _, msg = M.decode_can(frame.arbitration_id, bytes(frame.data))
        except M.FrameError as exc:
            self._drops[exc.cause] += 1
            return []
        return [(msg, None)]

    def _close(self) -> None:
        if self._own_bus:
            self.bus.shutdown()


#: backend name -> (module, class); imported lazily by :func:`open_link`
BACKENDS: dict[str, tuple[str, str]] = {
    "serial": ("host.link.clients", "SerialLink"),
    "can": ("host.link.clients", "CanLink"),
}


def open_link(spec: str, *, node_id: int = 1, baudrate: int = BOARD_BAUD) -> Link:
    """Open a link from a one-line spec.

    ``"loop://"``, ``"/dev/ttyACM0"``, ``"serial:/dev/ttyUSB0"`` -> :class:`SerialLink`;
    ``"can:INTERFACE:CHANNEL"`` (e.g. ``"can:socketcan:can0"``, ``"can:virtual:x"``,
    ``"can:serial:/dev/pts/3"``) -> :class:`CanLink`.

    Raises
    ------
    LinkError
        If the port or bus cannot be opened.
    ValueError
        If the spec is malformed.
    """
    kind, _, rest = spec.partition(":")
    if kind == "can":
        interface, _, channel = rest.partition(":")
        if not interface or not channel:
            raise ValueError(f"CAN link spec must be can:INTERFACE:CHANNEL, got {spec!r}")
        mod, cls = BACKENDS["can"]
        return getattr(importlib.import_module(mod), cls)(node_id=node_id, interface=interface, channel=channel)
    url = rest if kind == "serial" else spec
    mod, cls = BACKENDS["serial"]
    return getattr(importlib.import_module(mod), cls)(url, baudrate=baudrate)
