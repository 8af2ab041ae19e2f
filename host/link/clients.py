"""Host link clients: one :class:`Link` API over serial (pyserial) or CAN (python-can).

The base class owns the template method :meth:`Link.recv` and request/response with
timeouts and retries; transports implement ``_send(msg, seq)`` and
``_recv_internal(timeout)``.  Backends are chosen by name from :data:`BACKENDS` and
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
import select
import time
from typing import Any

from firmware import msgtable as T
from host.link import messages as M

__all__ = [
    "LinkError",
    "LinkTimeout",
    "LinkClosed",
    "CommandRefused",
    "Link",
    "SerialLink",
    "CanLink",
    "BACKENDS",
    "open_link",
]


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


# reply class wanted by a request, by request message name (default: ACK)
_REPLY: dict[str, str] = {"param_get": "param_value", "param_set": "param_value"}


class Link:
    """Abstract link: typed messages in and out.

    Parameters
    ----------
    backlog : int
        Messages kept for :meth:`recv` while :meth:`request` waits for its reply.
    """

    def __init__(self, *, backlog: int = 10000) -> None:
        self._queue: collections.deque[tuple[M.Message, int | None]] = collections.deque(maxlen=backlog)
        self._seq = 0
        self._closed = False
        self.last_seq: int | None = None
        self.sent = 0
        self.received = 0

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

    @property
    def drops(self) -> dict[str, int]:
        """Frames dropped by the receiver, by cause."""
        return {}

    # ---- public API ----
    def send(self, msg: M.Message) -> int:
        """Send one message; return the sequence number used (serial framing).

        Raises
        ------
        LinkError
        """
        if self._closed:
            raise LinkClosed("link is closed")
        if not isinstance(msg, M.Message):
            raise TypeError(f"expected a protocol message, got {type(msg).__name__}")
        seq = self._seq
        self._seq = (seq + 1) & 0xFF
        self._send(msg, seq)
        self.sent += 1
        return seq

    def recv(self, timeout: float | None = None) -> M.Message | None:
        """Next received message, or ``None`` when ``timeout`` s pass without one.

        ``timeout=None`` waits forever; ``0`` polls.  The serial sequence number of the
        returned message is in :attr:`last_seq` (``None`` on CAN).
        """
        if self._closed:
            raise LinkClosed("link is closed")
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._queue:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            got = self._recv_internal(left)
            self.received += len(got)
            self._queue.extend(got)
            if not self._queue and deadline is not None and time.monotonic() >= deadline:
                return None
        msg, self.last_seq = self._queue.popleft()
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
        deadline = time.monotonic() + timeout
        held: list[tuple[M.Message, int | None]] = []
        try:
            while True:
                while self._queue:
                    item = self._queue.popleft()
                    if match(*item):
                        self.last_seq = item[1]
                        return item[0]
                    held.append(item)
                left = deadline - time.monotonic()
                if left <= 0:
                    raise LinkTimeout(what)
                got = self._recv_internal(left)
                self.received += len(got)
                self._queue.extend(got)
        finally:
            self._queue.extendleft(reversed(held))

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
        """
        if reply is None:
            if msg.NAME == "request":
                reply = M.MESSAGES[getattr(msg, "msg_id")]
            else:
                reply = _REPLY.get(msg.NAME, "ack")
        cls = M.message_class(reply) if isinstance(reply, str) else reply

        sent: set[int] = set()

        def match(m: M.Message, seq: int | None) -> bool:
            # replies carry the seq of the request they answer (serial); a late reply
            # to an earlier request stays queued for recv()
            if seq is not None and seq not in sent:
                return False
            if isinstance(m, M.BY_NAME["nack"]) and m.msg_id == msg.ID:
                return True
            if isinstance(m, M.BY_NAME["ack"]):
                return cls.NAME == "ack" and m.msg_id == msg.ID
            if cls.NAME == "param_value":
                return isinstance(m, cls) and m.index == getattr(msg, "index")
            return isinstance(m, cls)

        for attempt in range(retries + 1):
            sent.add(self.send(msg))
            try:
                m = self._wait(match, timeout, "")
            except LinkTimeout:
                continue
            if m.NAME == "nack":
                raise CommandRefused(m.msg_id, m.reason)
            return m
        raise LinkTimeout(f"no answer to {msg.NAME} after {retries + 1} attempts of {timeout} s")

    # ---- commands ----
    def arm(self, **kw: Any) -> None:
        """Arm the motor (refused while a fault is latched)."""
        self.request(M.BY_NAME["arm"](), **kw)

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
        self.request(M.BY_NAME["gains_begin"](nbytes=len(table), crc=M.crc16(table)), **kw)
        n = T.CHUNK_BYTES
        for off in range(0, len(table), n):
            data = table[off:off + n].ljust(n, b"\x00")
            self.request(M.BY_NAME["gains_chunk"](offset=off, data=data), **kw)
        self.request(M.BY_NAME["gains_commit"](), **kw)

    # ---- lifetime ----
    def close(self) -> None:
        """Release the port or bus (idempotent)."""
        if not self._closed:
            self._closed = True
            self._close()

    def __enter__(self) -> "Link":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _param_index(param: int | str) -> int:
    if isinstance(param, str):
        try:
            return M.PARAMS[param][0]
        except KeyError:
            raise ValueError(f"unknown parameter {param!r}; known: {', '.join(M.PARAMS)}") from None
    return int(param)


class SerialLink(Link):
    """Serial framing over pyserial (any ``serial_for_url`` URL: a device, ``loop://``, a pty).

    Parameters
    ----------
    url : str
        Port or URL.
    baudrate : int
        Baud rate (ignored by ptys and USB CDC).
    backlog : int
        See :class:`Link`.
    """

    def __init__(self, url: str, baudrate: int = 115200, *, backlog: int = 10000) -> None:
        super().__init__(backlog=backlog)
        import serial

        self._serial_mod = serial
        try:
            self._ser = serial.serial_for_url(url, baudrate=baudrate, timeout=0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkError(f"cannot open serial port {url!r}: {exc}") from exc
        self.url = url
        self.decoder = M.SerialStreamDecoder()
        # the port stays non-blocking (timeout 0): waiting is a select() on its file
        # descriptor when it has one (changing a pyserial timeout reconfigures the tty)
        try:
            self._fd: int | None = self._ser.fileno()
        except (AttributeError, OSError, ValueError, serial.SerialException):
            self._fd = None

    @property
    def drops(self) -> dict[str, int]:
        return dict(self.decoder.drops)

    def _send(self, msg: M.Message, seq: int) -> None:
        try:
            self._ser.write(M.encode_serial(msg, seq))
            self._ser.flush()
        except (self._serial_mod.SerialException, OSError) as exc:
            raise LinkError(f"write to {self.url!r} failed: {exc}") from exc

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
    **bus_kwargs
        Passed to ``can.Bus`` when ``bus`` is not given.
    """

    def __init__(self, bus: Any = None, *, node_id: int = 1, backlog: int = 10000, **bus_kwargs: Any) -> None:
        super().__init__(backlog=backlog)
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
        self._drops = {"unknown": 0, "length": 0, "other": 0}

    @property
    def drops(self) -> dict[str, int]:
        return dict(self._drops)

    def _send(self, msg: M.Message, seq: int) -> None:
        cid, data = M.encode_can(msg, self.node_id)
        frame = self._can.Message(arbitration_id=cid, data=data, is_extended_id=False)
        try:
            self.bus.send(frame)
        except (self._can.CanError, OSError, ValueError) as exc:
            raise LinkError(f"CAN send failed: {exc}") from exc

    def _recv_internal(self, timeout: float | None) -> list[tuple[M.Message, int | None]]:
        try:
            frame = self.bus.recv(timeout)
        except ValueError:
            # a malformed frame the interface could not parse (python-can's serial
            # interface raises ValueError for a DLC > 8): dropped and counted, the
            # interface resynchronises on the next frame
            self._drops["length"] += 1
            return []
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


def open_link(spec: str, *, node_id: int = 1, baudrate: int = 115200) -> Link:
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
