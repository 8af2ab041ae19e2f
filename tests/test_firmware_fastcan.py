"""The CAN link's viper payload packer (firmware/fastcan.py) gives codec.Layout.pack's bytes.

Every message of the table, with values across each field's range (extremes included) and raw-byte
fields left as the caller put them, packs to the same payload and length on the MicroPython unix
port (real viper code, heap locked: no allocation) and under CPython (the decorator falls back to
a plain function).  A few seconds.
"""

from __future__ import annotations

from array import array

from firmware import codec, fastcan
from host.boards.mpyrun import run_unix
from test_proto_fastframe import _cases


def _cid(mid: int) -> int:
    return (((mid * 7) & 0x3F) << 5) | (mid & 0x1F)  # a node id per case: every id bit used


def _pack_all(fast: bool) -> list[bytes]:
    # per case: the pack's length and payload, then the whole transmit slot (link_can's bytes)
    lay = codec.Layout()
    res = []
    for mid, _seq, vals, voff, rawb in _cases():
        q = bytearray(6) + bytearray(rawb)
        v = array("i", vals)
        n = fastcan.pack_viper(lay.codes, lay.nfields, v, voff, mid, q, 6) if fast else lay.pack(mid, v, voff, q, 6)
        res.append(bytes([n]) + bytes(q[6:]))
        q = bytearray(6) + bytearray(rawb)
        if fast:
            n = fastcan.frame_viper(lay.codes, lay.nfields, v, voff, mid, q, _cid(mid))
        else:
            n = lay.pack(mid, v, voff, q, 6)
            c = _cid(mid)
            q[1:6] = bytes([c >> 3, (c & 7) << 5, 0, 0, n])  # link_can.CanLink._fill
        res.append(bytes([n]) + bytes(q))
    return res


def test_cpython_fallback_equals_codec() -> None:
    ref = _pack_all(False)
    assert _pack_all(True) == ref
    assert any(r[0] == 8 for r in ref) and len(set(ref)) > len(ref) // 2  # (the cases vary)


SCRIPT = """
from array import array
import micropython
from firmware import codec
from firmware.fastcan import pack_viper, frame_viper
lay = codec.Layout()
bad = 0
q = bytearray(14)
for i in range(len(CASES)):
    mid, seq, vals, voff, rawb = CASES[i]
    q[6:14] = rawb
    n = pack_viper(lay.codes, lay.nfields, array('i', vals), voff, mid, q, 6)
    if bytes([n]) + bytes(q[6:14]) != EXPECT[2 * i]:
        bad += 1
    q = bytearray(6) + bytearray(rawb)
    n = frame_viper(lay.codes, lay.nfields, array('i', vals), voff, mid, q, (((mid * 7) & 0x3F) << 5) | (mid & 0x1F))
    if bytes([n]) + bytes(q) != EXPECT[2 * i + 1]:
        bad += 1
print('bad', bad)
tx = array('i', [1, -2, 3, -4, 5, -6, 7, 8])
pack_viper(lay.codes, lay.nfields, tx, 0, 4, q, 6)
micropython.heap_lock()
try:
    for k in range(200):
        pack_viper(lay.codes, lay.nfields, tx, 0, 4, q, 6)
        pack_viper(lay.codes, lay.nfields, tx, 4, 5, q, 6)
        frame_viper(lay.codes, lay.nfields, tx, 4, 5, q, 37)
    ok = 1
except MemoryError:
    ok = 0
micropython.heap_unlock()
print('alloc_free', ok)
"""


def test_viper_equals_codec_on_micropython_and_allocates_nothing() -> None:
    cases = _cases()
    script = f"CASES = {[(m, s, v, o, r) for m, s, v, o, r in cases]!r}\nEXPECT = {_pack_all(False)!r}\n" + SCRIPT
    out = dict(line.split() for line in run_unix(script, timeout=120).splitlines() if line.strip())
    assert out["bad"] == "0" and out["alloc_free"] == "1", out
