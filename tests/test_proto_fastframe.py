"""The viper and native frame encoders (firmware/fastframe.py) give the bytecode's bytes.

``framing.Encoder(layout, table, emitter)`` with ``"viper"`` or ``"native"`` packs, CRCs and
COBS-stuffs a frame in one call; with ``"bytecode"`` it takes the plain path of framing.py.
Every message of the table, with values across each field's range (extremes included) and
sequence numbers across 0..255, encodes to the same wire bytes on all three paths: under the
MicroPython unix port (real viper/native code), under CPython (the decorators fall back to
plain functions) and -- bytecode only, the port has no native emitter -- on the 32-bit
WebAssembly port against CPython's bytes.  ``fastlink.telem_viper`` gives
``App.fill_telemetry``'s values; the fast paths allocate nothing.
"""

from __future__ import annotations

import random
from array import array

import pytest

from firmware import codec, crc16, framing
from firmware import msgtable as T
import fwharness as H
from host.boards.mpyrun import run_unix, run_wasm

_RANGES = {"B": (0, 255), "b": (-128, 127), "H": (0, 65535), "h": (-32768, 32767),
           "I": (0, 2**30 - 1), "i": (-(2**30 - 1), 2**30 - 1)}


def _cases(n_random: int = 12) -> list[tuple[int, int, list[int], int, bytes]]:
    """(mid, seq, vals, voff, raw payload bytes) for every message: extremes and random values."""
    rng = random.Random(12)
    out = []
    for mid, _name, _d, _doc, fields in T.MESSAGES:
        fmts = [f[1] for f in fields]
        for k in range(n_random + 3):
            voff = k % 3
            vals = [0] * voff
            for f in fmts:
                if f.endswith("s"):
                    vals.append(0)
                    continue
                lo, hi = _RANGES[f]
                vals.append(lo if k == 0 else hi if k == 1 else 0 if k == 2 else rng.randint(lo, hi))
            vals += [rng.randint(-5, 5) for _ in range(8 - len(vals) + voff)]
            rawb = bytes(rng.randrange(256) if k > 2 else (0 if k == 2 else 255) for _ in range(8))
            out.append((mid, (k * 37 + mid) & 0xFF, vals, voff, rawb))
    return out


def _encode_all(emitter: str) -> list[bytes]:
    lay = codec.Layout()
    enc = framing.Encoder(lay, crc16.make_table(), emitter)
    res = []
    for mid, seq, vals, voff, rawb in _cases():
        enc.raw[2:10] = rawb  # raw-byte fields keep what the caller put there
        n = enc.encode(mid, seq, array("i", vals), voff)
        res.append(bytes(enc.out[:n]))
        n = enc.encode(mid, seq, vals, voff)  # a list: the plain path
        res.append(bytes(enc.out[:n]))
    return res


def test_cpython_fallback_equals_bytecode() -> None:
    ref = _encode_all("bytecode")
    assert _encode_all("viper") == ref
    assert _encode_all("native") == ref
    # and the bytecode path decodes back to the values (framing.Decoder)
    lay = codec.Layout()
    dec = framing.Decoder(lay, crc16.make_table())
    got = 0
    for wire in ref:
        for b in wire:
            if dec.feed(b) >= 0:
                got += 1
    assert got == len(ref)


def test_fast_path_refuses_what_bytecode_refuses() -> None:
    from firmware import fastframe as F

    lay = codec.Layout()
    lut = F.make_lut(lay, crc16.make_table())
    raw, out = bytearray(12), bytearray(15)
    F.set_vals_len(lut, 4)
    v = array("i", range(8))
    assert F.encode_viper(lut, raw, out, v, 0, 40, 0) == -1  # no such id
    assert F.encode_viper(lut, raw, out, v, 1, T.TELEM_STATE, 0) == -1  # fields past the checked length
    assert F.encode_viper(lut, raw, out, v, -1, T.TELEM_STATE, 0) == -1
    assert raw == bytearray(12) and out == bytearray(15)
    assert F.encode_viper(lut, raw, out, v, 0, T.TELEM_STATE, 0) > 0


SCRIPT = """
from array import array
from firmware import codec, crc16, framing
from firmware.app import App
import micropython
lay = codec.Layout()
tab = crc16.make_table()
encs = [framing.Encoder(lay, tab, em) for em in ('bytecode', 'viper', 'native')]
bad = 0
n_ok = 0
for mid, seq, vals, voff, rawb in CASES:
    outs = []
    for e in encs:
        e.raw[2:10] = rawb
        n = e.encode(mid, seq, array('i', vals), voff)
        outs.append(bytes(e.out[:n]))
    if outs[1] != outs[0] or outs[2] != outs[0]:
        bad += 1
    if outs[0] == EXPECT[n_ok]:
        n_ok += 1
print('bad', bad)
print('ok', n_ok)
# no allocation on the fast paths (the heap locked)
tx = array('i', [1, -2, 3, -4, 5, -6, 7, 8])
for em, e in (('viper', encs[1]), ('native', encs[2])):
    e.encode(4, 0, tx, 0)
    micropython.heap_lock()
    try:
        for k in range(200):
            e.encode(4, k, tx, 0)
            e.encode(5, k, tx, 4)
        ok = 1
    except MemoryError:
        ok = 0
    micropython.heap_unlock()
    print('alloc_free_' + em, ok)
""" + H.FAKE_HAL + """
a0 = App(Hal(), config={'watchdog_ms': 0})
a1 = App(Hal(), config={'watchdog_ms': 0, 'emitter': 'viper'})
t0 = array('i', [0] * 8)
t1 = array('i', [0] * 8)
tbad = 0
for k in range(400):
    for a in (a0, a1):
        c = a.ctrl
        s = 1 if k & 1 else -1
        c.xf[0] = s * (k * 2654435) % 4000000
        c.xf[2] = -s * (k * 40503) % 3000000
        c.xf[3] = s * (k * 9973) % 30000000
        c.vh = -s * (k * 7919) % 20000000
        c.u = s * (k * 131) % 60000
        a.ref = -s * (k * 17) % 200000
    a0.fill_telemetry(t0)
    a1.fill_telemetry(t1)
    if list(t0[:6]) != list(t1[:6]):
        tbad += 1
print('tbad', tbad)
"""


def _script() -> str:
    cases = _cases()
    expect = [b for i, b in enumerate(_encode_all("bytecode")) if i % 2 == 0]
    return f"CASES = {[(m, s, v, o, r) for m, s, v, o, r in cases]!r}\nEXPECT = {expect!r}\n" + SCRIPT


def test_viper_and_native_equal_bytecode_unix() -> None:
    out = dict(line.split() for line in run_unix(_script(), timeout=120).splitlines() if line.strip())
    assert out["bad"] == "0" and int(out["ok"]) == len(_cases())
    assert out["alloc_free_viper"] == "1" and out["alloc_free_native"] == "1"
    assert out["tbad"] == "0"


@pytest.mark.wasm
def test_bytecode_on_32bit_wasm_equals_cpython() -> None:
    cases = _cases()
    expect = [b for i, b in enumerate(_encode_all("bytecode")) if i % 2 == 0]
    code = f"CASES = {cases!r}\nEXPECT = {expect!r}\n" + """
from array import array
from firmware import codec, crc16, framing
enc = framing.Encoder(codec.Layout(), crc16.make_table())
ok = 0
for i, (mid, seq, vals, voff, rawb) in enumerate(CASES):
    enc.raw[2:10] = rawb
    n = enc.encode(mid, seq, array('i', vals), voff)
    if bytes(enc.out[:n]) == EXPECT[i]:
        ok += 1
print('ok', ok)
"""
    out = dict(line.split() for line in run_wasm(code, timeout=120).splitlines() if line.strip())
    assert int(out["ok"]) == len(cases)
