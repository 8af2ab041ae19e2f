"""Shared helpers of the protocol tests (not a test module)."""

from __future__ import annotations

from array import array

from hypothesis import strategies as st

from firmware import codec, framing
from host import messages as M


def message_strategy(cls: type[M.Message] | None = None) -> st.SearchStrategy[M.Message]:
    """Any message of the table (or of one class) with arbitrary in-range raw fields."""
    if cls is None:
        return st.sampled_from(list(M.MESSAGES.values())).flatmap(message_strategy)
    kw = {}
    for f in cls.FIELDS:
        if f.is_raw:
            kw[f.name] = st.binary(min_size=f.size, max_size=f.size)
        else:
            lo, hi = f.bounds
            kw[f.name] = st.integers(lo, hi)
    return st.builds(cls, **kw)


def fw_small(f: M.Field, v: int) -> int:
    """What the firmware's unpack yields for a raw value (small-int rule)."""
    if f.fmt == "I":
        return v & 0x3FFFFFFF
    if f.fmt == "i":
        return max(-(2**30 - 1), min(2**30 - 1, v))
    return v


def fw_encode(msg: M.Message, seq: int) -> bytes:
    """Serial wire bytes produced by the firmware encoder (under CPython)."""
    layout = codec.Layout()
    enc = framing.Encoder(layout)
    vals = array("i", [0] * 8)
    for k, f in enumerate(msg.FIELDS):
        if not f.is_raw:
            vals[k] = getattr(msg, f.name) if f.fmt != "I" else getattr(msg, f.name) - (1 << 32 if getattr(msg, f.name) >= 1 << 31 else 0)
    off = 2
    for f in msg.FIELDS:
        if f.is_raw:
            enc.raw[off:off + f.size] = getattr(msg, f.name)
        off += f.size
    n = layout.pack(msg.ID, vals, 0, enc.raw, 2)
    return bytes(enc.out[: enc.frame(msg.ID, seq, n)])


def fw_decode_stream(data: bytes) -> tuple[list[tuple[int, int, bytes]], dict[str, int]]:
    """Run the firmware decoder (CPython) over ``data``: frames and drop counters."""
    layout = codec.Layout()
    dec = framing.Decoder(layout)
    out = []
    for b in data:
        m = dec.feed(b)
        if m >= 0:
            out.append((m, dec.seq, bytes(dec.buf[2:2 + dec.plen])))
    return out, {"crc": dec.n_crc, "length": dec.n_length, "unknown": dec.n_unknown, "overrun": dec.n_overrun}
