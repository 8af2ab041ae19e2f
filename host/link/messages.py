"""Typed protocol messages generated from :mod:`firmware.msgtable`, and both framings.

Every row of ``firmware.msgtable.MESSAGES`` becomes a frozen dataclass (``Heartbeat``,
``HilSensor``, ``SetReference``, ...) whose fields are the raw wire integers (``bytes``
for raw fields), so ``decode(encode(m)) == m`` exactly; :meth:`Message.physical` and
:meth:`Message.from_physical` convert with the table's scales and units.

Framings (an implementation independent of the firmware's, used to cross-check it):

* serial: ``0x00 COBS([id][seq][payload][crc16 big-endian]) 0x00`` with
  CRC-16/CCITT-FALSE (``binascii.crc_hqx(data, 0xFFFF)``);
* CAN: 11-bit id ``node_id << 5 | msg_id``, DLC = payload length, little-endian; on a
  byte stream (python-can's ``serial`` interface) each frame carries a CRC-16 of its own
  in the timestamp field (:func:`serial_can_crc`, :func:`encode_serial_can`).
"""

from __future__ import annotations

import binascii
import dataclasses
import math
import struct
import zlib
from typing import Any, ClassVar, Iterator

from firmware import msgtable as T

__all__ = [
    "Field",
    "command_check",
    "table_check",
    "STATUS",
    "Message",
    "ProtocolError",
    "FrameError",
    "CRCError",
    "LengthError",
    "UnknownMessageError",
    "OverrunError",
    "MESSAGES",
    "BY_NAME",
    "REASONS",
    "REASON_NAMES",
    "PARAMS",
    "STATES",
    "crc16",
    "cobs_encode",
    "cobs_decode",
    "encode_serial",
    "decode_serial",
    "SerialStreamDecoder",
    "can_id",
    "split_can_id",
    "encode_can",
    "decode_can",
    "serial_can_crc",
    "encode_serial_can",
    "message_class",
    "make",
]


class ProtocolError(ValueError):
    """A message or frame that does not follow the protocol."""


class FrameError(ProtocolError):
    """A received frame was dropped (base of the drop causes)."""

    cause = "frame"


class CRCError(FrameError):
    """The frame's CRC-16/CCITT-FALSE does not check out."""

    cause = "crc"


class LengthError(FrameError):
    """Truncated, malformed COBS, or payload length wrong for the message id."""

    cause = "length"


class UnknownMessageError(FrameError):
    """The message id is not in the table."""

    cause = "unknown"


class OverrunError(FrameError):
    """The frame is longer than the largest frame of the protocol."""

    cause = "overrun"


_RANGES = {"B": (0, 0xFF), "b": (-128, 127), "H": (0, 0xFFFF), "h": (-32768, 32767),
           "I": (0, 0xFFFFFFFF), "i": (-(2**31), 2**31 - 1)}


@dataclasses.dataclass(frozen=True)
class Field:
    """One field of a message: name, struct format, scale, unit and documentation."""

    name: str
    fmt: str
    scale: float
    unit: str
    doc: str

    @property
    def size(self) -> int:
        """Size in bytes on the wire."""
        return struct.calcsize("<" + self.fmt)

    @property
    def is_raw(self) -> bool:
        """True for raw byte fields (``Ns``)."""
        return self.fmt.endswith("s")

    @property
    def signed(self) -> bool:
        """True for signed integer fields."""
        return self.fmt in ("b", "h", "i")

    @property
    def bounds(self) -> tuple[int, int]:
        """Smallest and largest raw value that fits the format."""
        return _RANGES[self.fmt]


class Message:
    """Base of the generated message classes.

    Class attributes ``ID``, ``NAME``, ``DIRECTION`` (``"to_board"``/``"to_host"``),
    ``DOC``, ``FIELDS`` and ``STRUCT`` describe the message; instances hold raw values.
    """

    ID: ClassVar[int]
    NAME: ClassVar[str]
    DIRECTION: ClassVar[str]
    DOC: ClassVar[str]
    FIELDS: ClassVar[tuple[Field, ...]]
    STRUCT: ClassVar[struct.Struct]

    #: the field a message of :data:`firmware.msgtable.CHECKED` ends in: filled in by the
    #: constructor when not given (:func:`command_check`)
    AUTO_CHECK: ClassVar[str | None] = None

    def __post_init__(self) -> None:
        if self.AUTO_CHECK is not None and getattr(self, self.AUTO_CHECK) is None:
            object.__setattr__(self, self.AUTO_CHECK, _check_value(self))
        for f in self.FIELDS:
            v = getattr(self, f.name)
            if f.is_raw:
                if not isinstance(v, (bytes, bytearray)) or len(v) != f.size:
                    raise ProtocolError(f"{self.NAME}.{f.name} must be {f.size} bytes, got {v!r}")
                object.__setattr__(self, f.name, bytes(v))
                continue
            if isinstance(v, bool) or not isinstance(v, int):
                raise ProtocolError(f"{self.NAME}.{f.name} must be an int (raw wire value), got {v!r}")
            lo, hi = f.bounds
            if not lo <= v <= hi:
                raise ProtocolError(f"{self.NAME}.{f.name}={v} outside {f.fmt} range [{lo}, {hi}]")

    # ---- payload ----
    def values(self) -> tuple[Any, ...]:
        """Raw field values in table order."""
        return tuple(getattr(self, f.name) for f in self.FIELDS)

    def payload(self) -> bytes:
        """The little-endian payload (identical in both framings)."""
        return self.STRUCT.pack(*self.values())

    @classmethod
    def from_payload(cls, data: bytes) -> "Message":
        """Decode a payload of exactly this message's length.

        Raises
        ------
        LengthError
            If ``len(data)`` differs from the message's payload length.
        """
        if len(data) != cls.STRUCT.size:
            raise LengthError(f"{cls.NAME}: payload of {len(data)} bytes, expected {cls.STRUCT.size}")
        return cls(*cls.STRUCT.unpack(bytes(data)))

    # ---- units ----
    def physical(self) -> dict[str, Any]:
        """Field values in physical units (raw * scale; raw bytes unchanged)."""
        out: dict[str, Any] = {}
        for f in self.FIELDS:
            v = getattr(self, f.name)
            out[f.name] = v if f.is_raw or f.scale == 1 else v * f.scale
        return out

    @classmethod
    def from_physical(cls, **values: Any) -> "Message":
        """Build from physical values (rounded to the nearest raw step).

        Raises
        ------
        ProtocolError
            Unknown or missing field, a non-finite value, or a value out of range.
        """
        names = {f.name for f in cls.FIELDS}
        extra = set(values) - names
        if extra:
            raise ProtocolError(f"{cls.NAME}: unknown field(s) {sorted(extra)}")
        raw = {}
        for f in cls.FIELDS:
            if f.name not in values and f.name == cls.AUTO_CHECK:
                continue
            if f.name not in values:
                raise ProtocolError(f"{cls.NAME}: missing field {f.name}")
            v = values[f.name]
            if f.is_raw:
                raw[f.name] = v
                continue
            if not math.isfinite(float(v)):
                raise ProtocolError(f"{cls.NAME}.{f.name} is not finite: {v!r}")
            raw[f.name] = int(round(float(v) / f.scale))
        return cls(**raw)

    def __str__(self) -> str:
        parts = []
        for f in self.FIELDS:
            v = getattr(self, f.name)
            if f.is_raw:
                parts.append(f"{f.name}={v.hex()}")
            elif f.scale != 1:
                parts.append(f"{f.name}={v * f.scale:.6g}{f.unit}")
            else:
                parts.append(f"{f.name}={v}{f.unit}")
        extra = ""
        if self.NAME == "nack":
            extra = f" ({REASON_NAMES.get(getattr(self, 'reason'), '?')})"
        return f"{self.NAME}({', '.join(parts)}){extra}"


def _camel(name: str) -> str:
    return "".join(p.capitalize() for p in name.split("_"))


def command_check(msg: Message) -> int:
    """The integrity check of a command that moves the cart (``firmware.msgtable.CHECKED``).

    CRC-32/ISO-HDLC (:func:`zlib.crc32`) over the message id byte and the payload bytes before
    the trailing ``check`` field, truncated to that field's width (u32: all 32 bits, of which
    the firmware compares the low 30; ``param_set``'s 3 raw bytes: the low 24 bits, little-endian).
    """
    flds = msg.FIELDS[:-1]
    body = struct.pack("<" + "".join(f.fmt for f in flds), *(getattr(msg, f.name) for f in flds))
    crc = zlib.crc32(bytes([msg.ID]) + body)
    return crc & ((1 << (8 * msg.FIELDS[-1].size)) - 1)


def _check_value(msg: Message) -> int | bytes:
    # the check as the field holds it: an int, or little-endian bytes for a raw field
    v = command_check(msg)
    f = msg.FIELDS[-1]
    return v.to_bytes(f.size, "little") if f.is_raw else v


def table_check(table: bytes) -> int:
    """``gains_commit.check``: the CRC-32 (:func:`zlib.crc32`) of the whole gain table."""
    return zlib.crc32(bytes(table))


def _build() -> dict[int, type[Message]]:
    out: dict[int, type[Message]] = {}
    for mid, name, direction, doc, fields in T.MESSAGES:
        flds = tuple(Field(*f) for f in fields)
        auto = mid in T.CHECKED and flds and flds[-1].name == "check"
        dc_fields: list[Any] = [(f.name, bytes if f.is_raw else int) for f in flds]
        if auto:
            dc_fields[-1] = ("check", "int | bytes | None", dataclasses.field(default=None))
        ns = {
            "ID": mid,
            "NAME": name,
            "DIRECTION": "to_board" if direction == T.TO_BOARD else "to_host",
            "DOC": doc,
            "FIELDS": flds,
            "STRUCT": struct.Struct("<" + "".join(f.fmt for f in flds)),
            "AUTO_CHECK": "check" if auto else None,
            "__doc__": f"{doc}\n\nFields (raw wire values): "
            + (", ".join(f"{f.name} ({f.fmt}, x{f.scale} {f.unit})".rstrip() for f in flds) or "none"),
        }
        cls = dataclasses.make_dataclass(_camel(name), dc_fields, bases=(Message,), frozen=True, namespace=ns)
        cls.__module__ = __name__
        out[mid] = cls
    return out


#: message id -> class
MESSAGES: dict[int, type[Message]] = _build()
#: message name -> class
BY_NAME: dict[str, type[Message]] = {c.NAME: c for c in MESSAGES.values()}
globals().update({c.__name__: c for c in MESSAGES.values()})
__all__ += [c.__name__ for c in MESSAGES.values()]

#: reason code -> (name, doc)
REASONS: dict[int, tuple[str, str]] = {code: (name, doc) for code, name, doc in T.REASONS}
REASON_NAMES: dict[int, str] = {code: name for code, (name, _) in REASONS.items()}
#: parameter name -> (index, unit, min, max, default, doc)
PARAMS: dict[str, tuple[int, str, int, int, int, str]] = {p[1]: (p[0], p[2], p[3], p[4], p[5], p[6]) for p in T.PARAMS}
STATES: dict[int, str] = {s[0]: s[1] for s in T.STATES}
#: status value name -> (param_get index, unit, doc): read-only board figures (msgtable STATUS)
STATUS: dict[str, tuple[int, str, str]] = {s[1]: (T.STATUS_BASE + s[0], s[2], s[3]) for s in T.STATUS}


def message_class(key: int | str) -> type[Message]:
    """The message class for an id or a name.

    Raises
    ------
    UnknownMessageError
    """
    try:
        return MESSAGES[key] if isinstance(key, int) else BY_NAME[key]
    except KeyError:
        raise UnknownMessageError(f"no message {key!r}; known: {', '.join(BY_NAME)}") from None


def make(name: str, **raw: Any) -> Message:
    """Build a message by name from raw field values (``make("param_get", index=3)``)."""
    return message_class(name)(**raw)


# ---------------------------------------------------------------- serial framing
def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0)."""
    return binascii.crc_hqx(bytes(data), 0xFFFF)


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing (no delimiter added)."""
    out = bytearray()
    block = bytearray()
    for b in data:
        if b == 0:
            out.append(len(block) + 1)
            out += block
            block.clear()
        else:
            block.append(b)
            if len(block) == 254:
                out.append(255)
                out += block
                block.clear()
    out.append(len(block) + 1)
    out += block
    return bytes(out)


def _cobs_lenient(data: bytes) -> tuple[bytes, bool]:
    # decoded bytes (a zero between blocks, as the firmware puts them) and
    # whether the last block was complete
    out = bytearray()
    i = 0
    n = len(data)
    zero = False
    while i < n:
        code = data[i]
        if zero:
            out.append(0)
        block = data[i + 1:i + code]
        out += block
        if len(block) < code - 1:
            return bytes(out), False
        i += code
        zero = code != 0xFF
    return bytes(out), True


def cobs_decode(data: bytes) -> bytes:
    """Undo :func:`cobs_encode`.

    Raises
    ------
    LengthError
        If a block is truncated or a 0x00 is inside the data.
    """
    if 0 in data:
        raise LengthError("0x00 inside a COBS frame")
    out, ok = _cobs_lenient(data)
    if not ok or not data:
        raise LengthError("truncated COBS block")
    return out


def encode_serial(msg: Message, seq: int = 0) -> bytes:
    """Serial wire bytes of ``msg`` (with both 0x00 delimiters)."""
    raw = bytes([msg.ID, seq & 0xFF]) + msg.payload()
    raw += crc16(raw).to_bytes(2, "big")
    return b"\x00" + cobs_encode(raw) + b"\x00"


def _check_raw(raw: bytes) -> tuple[Message, int]:
    if len(raw) < 4:
        raise LengthError(f"frame of {len(raw)} bytes is shorter than id+seq+crc")
    if crc16(raw) != 0:
        raise CRCError(f"CRC mismatch (frame {raw.hex()})")
    cls = MESSAGES.get(raw[0])
    if cls is None:
        raise UnknownMessageError(f"unknown message id {raw[0]}")
    return cls.from_payload(raw[2:-2]), raw[1]


def decode_serial(frame: bytes) -> tuple[Message, int]:
    """Decode one serial frame (delimiters optional) into ``(message, seq)``.

    Raises
    ------
    FrameError
        :class:`CRCError`, :class:`LengthError`, :class:`UnknownMessageError` or
        :class:`OverrunError`.
    """
    body = bytes(frame).strip(b"\x00")
    if not body:
        raise LengthError("empty frame")
    raw = cobs_decode(body)
    if len(raw) > T.MAX_FRAME:
        raise OverrunError(f"frame of {len(raw)} bytes exceeds {T.MAX_FRAME}")
    return _check_raw(raw)


class SerialStreamDecoder:
    """Incremental serial decoder: feed bytes, get ``(message, seq)`` pairs.

    Drop counters by cause (``drops["crc"|"length"|"unknown"|"overrun"]``) follow the
    same rules as the firmware decoder, so the two can be compared byte for byte.

    Parameters
    ----------
    mid_stream : bool
        The stream may begin inside a frame (a port opened while the board talks, or holding
        the rest of a frame another tool read half of): a first chunk that does not decode is
        the tail of a frame sent before this decoder listened. It is counted in
        :attr:`joined`, not as a drop. A first chunk that decodes is kept.
    """

    def __init__(self, *, mid_stream: bool = False) -> None:
        self._buf = bytearray()
        self.drops: dict[str, int] = {"crc": 0, "length": 0, "unknown": 0, "overrun": 0}
        self.ok = 0
        #: bytes of a first chunk that did not decode (``mid_stream``): a frame joined halfway
        self.joined = 0
        self._first = mid_stream

    def feed(self, data: bytes) -> list[tuple[Message, int]]:
        """Consume ``data``; return every complete valid frame in order."""
        out = []
        for chunk in self._split(bytes(data)):
            res = self._one(chunk)
            if res is not None:
                out.append(res)
        return out

    def _split(self, data: bytes) -> Iterator[bytes]:
        start = 0
        while True:
            j = data.find(b"\x00", start)
            if j < 0:
                self._buf += data[start:]
                if len(self._buf) > 4 * T.MAX_WIRE:
                    # keep memory bounded; long garbage is an overrun anyway
                    self._buf = self._buf[:2 * T.MAX_WIRE]
                return
            chunk = bytes(self._buf) + data[start:j]
            self._buf.clear()
            start = j + 1
            if chunk:
                yield chunk

    def _one(self, chunk: bytes) -> tuple[Message, int] | None:
        raw, complete = _cobs_lenient(chunk)
        try:
            if len(raw) > T.MAX_FRAME:
                raise OverrunError("overrun")
            if not complete:
                raise LengthError("truncated")
            res = _check_raw(raw)
        except FrameError as exc:
            if self._first:
                self._first = False
                self.joined += len(chunk)
                return None
            self.drops[exc.cause] += 1
            return None
        self._first = False
        self.ok += 1
        return res


# ---------------------------------------------------------------- CAN framing
def can_id(node_id: int, msg_id: int) -> int:
    """11-bit arbitration id ``node_id << 5 | msg_id``."""
    if not 0 <= node_id < 2**T.NODE_BITS:
        raise ProtocolError(f"node_id {node_id} outside 0..{2**T.NODE_BITS - 1}")
    if not 0 <= msg_id <= T.MAX_ID:
        raise ProtocolError(f"msg_id {msg_id} outside 0..{T.MAX_ID}")
    return node_id << T.MSG_BITS | msg_id


def split_can_id(arbitration_id: int) -> tuple[int, int]:
    """``(node_id, msg_id)`` of an 11-bit arbitration id."""
    if not 0 <= arbitration_id <= 0x7FF:
        raise ProtocolError(f"arbitration id {arbitration_id:#x} is not an 11-bit id")
    return arbitration_id >> T.MSG_BITS, arbitration_id & T.MAX_ID


def encode_can(msg: Message, node_id: int) -> tuple[int, bytes]:
    """``(arbitration_id, data)`` of ``msg`` for node ``node_id``."""
    return can_id(node_id, msg.ID), msg.payload()


def decode_can(arbitration_id: int, data: bytes) -> tuple[int, Message]:
    """``(node_id, message)`` from a CAN frame.

    Raises
    ------
    UnknownMessageError, LengthError
    """
    node, mid = split_can_id(arbitration_id)
    cls = MESSAGES.get(mid)
    if cls is None:
        raise UnknownMessageError(f"unknown message id {mid} (CAN id {arbitration_id:#x})")
    return node, cls.from_payload(bytes(data))


# ---------------------------------------------------------------- CAN frames on a byte stream
def serial_can_crc(arbitration_id: int, data: bytes) -> int:
    """CRC of a CAN frame carried as python-can ``serial``-interface bytes.

    CRC-16/CCITT-FALSE over the DLC byte, the 4 little-endian arbitration-id bytes and the
    data; the frame carries it in its timestamp field (low 16 bits, high 16 bits 0), as
    ``firmware/canframe.py`` writes and checks it.
    """
    data = bytes(data)
    return crc16(bytes([len(data)]) + int(arbitration_id).to_bytes(4, "little") + data)


def encode_serial_can(msg: Message, node_id: int) -> bytes:
    """python-can ``serial``-interface bytes of ``msg`` for node ``node_id``, with the CRC.

    ``0xAA, crc u16 LE, 0, 0, dlc, arbitration id u32 LE, data, 0xBB``.
    """
    cid, data = encode_can(msg, node_id)
    crc = serial_can_crc(cid, data)
    return (b"\xaa" + crc.to_bytes(2, "little") + b"\x00\x00" + bytes([len(data)])
            + cid.to_bytes(4, "little") + data + b"\xbb")
