"""The generated CAN database decodes what the firmware encodes (cantools)."""

from __future__ import annotations

import functools
from array import array
from pathlib import Path

import cantools
from hypothesis import given, settings

from firmware import canframe, codec
from host.link import dbc
from host.link import protodoc
from host.link import messages as M
from proto_helpers import message_strategy

ROOT = Path(__file__).resolve().parent.parent


@functools.lru_cache(maxsize=1)
def _db():
    return cantools.database.load_file(str(ROOT / "docs" / "upright.dbc"))


def test_dbc_file_is_the_rendered_table():
    assert (ROOT / "docs" / "upright.dbc").read_text() == dbc.render_default()
    db = _db()
    assert {m.name for m in db.messages} == set(M.BY_NAME)
    for cls in M.MESSAGES.values():
        m = db.get_message_by_name(cls.NAME)
        assert m.frame_id == canframe.can_id(1, cls.ID) and m.length == cls.STRUCT.size
        assert [s.name for s in sorted(m.signals, key=lambda s: s.start)] == [f.name for f in cls.FIELDS]


@settings(max_examples=200)
@given(message_strategy())
def test_cantools_decodes_firmware_encoded_frames(msg):
    db = _db()
    layout = codec.Layout()
    vals = array("i", [0] * 8)
    data = bytearray(8)
    # firmware packing (values as the firmware holds them: small ints)
    for k, f in enumerate(msg.FIELDS):
        if not f.is_raw:
            v = getattr(msg, f.name)
            vals[k] = v - (1 << 32) if f.fmt == "I" and v >= 1 << 31 else v
    off = 0
    for f in msg.FIELDS:
        if f.is_raw:
            data[off:off + f.size] = getattr(msg, f.name)
        off += f.size
    n = layout.pack(msg.ID, vals, 0, data, 0)
    w = canframe.SerialCanWriter(layout, 1)
    w.data[:] = data
    wire = bytes(w.out[: w.frame(msg.ID, n, 0)])
    cid = int.from_bytes(wire[6:10], "little")
    payload = wire[10:-1]
    assert payload == msg.payload()
    got = db.decode_message(cid, payload, decode_choices=False, scaling=False)
    for f in msg.FIELDS:
        want = getattr(msg, f.name)
        assert got[f.name] == (int.from_bytes(want, "little") if f.is_raw else want), f.name
    scaled = db.decode_message(cid, payload, decode_choices=False)
    for name, v in msg.physical().items():
        if not isinstance(v, bytes):
            assert abs(scaled[name] - v) <= 1e-9 * max(1.0, abs(v))
    # and cantools' encoding is the same bytes
    assert db.encode_message(cid, got, scaling=False) == payload


def test_protocol_reference_names_everything():
    text = (ROOT / "docs" / "protocol.md").read_text()
    assert text == protodoc.render_protocol_md()
    for cls in M.MESSAGES.values():
        assert f"`{cls.NAME}`" in text
        for f in cls.FIELDS:
            assert f"`{f.name}`" in text
    for name in M.REASON_NAMES.values():
        assert f"`{name}`" in text
    for name in M.PARAMS:
        assert f"`{name}`" in text
    assert "CRC-16/CCITT-FALSE" in text
