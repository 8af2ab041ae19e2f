"""The firmware protocol modules under real MicroPython (unix port and 32-bit wasm).

* allocation-free: decoder, encoder and dispatcher run with ``micropython.heap_lock()``
  (unix) and with a zero ``gc.mem_alloc()`` delta (wasm) over thousands of random bytes
  mixed with valid frames (commands included);
* hypothesis generates byte streams on the host; MicroPython decodes a whole batch in
  one interpreter run and its frames and drop counters must equal the host's;
* a MicroPython "board" on a pty answers the host's SerialLink and python-can's
  ``serial`` interface (python-can parsing bytes written by MicroPython).
"""

from __future__ import annotations

import os
import random
import subprocess
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from host.link import clients as L
from host.link import messages as M
from host.boards.mpyrun import ROOT, micropython_exe, run_unix, run_wasm, standin_source, wasm_available
from proto_helpers import PtyBridge, message_strategy

_FEED = standin_source() + """
from array import array
from firmware import codec, framing, commands

class Sink:
    def __init__(self):
        self.n = 0
        self.bytes = 0
    def write(self, buf, n):
        self.n += 1
        self.bytes += n

layout = codec.Layout()
dec = framing.Decoder(layout)
sink = Sink()
tx = framing.SerialTx(framing.Encoder(layout), sink.write)
disp = commands.Dispatcher(StandIn(), layout, tx)
vals = array('i', [0] * 8)

def feed(data, n):
    ok = 0
    for i in range(n):
        m = dec.feed(data[i])
        if m >= 0:
            layout.unpack(m, dec.buf, 2, vals, 0)
            disp.handle(m, dec.seq, dec.buf, 2)
            ok += 1
    return ok

def scan(data, n):
    ok = 0
    i = 0
    while i < n:
        m = dec.scan(data, i, n)
        i = dec.next
        if m >= 0:
            layout.unpack(m, dec.buf, 2, vals, 0)
            disp.handle(m, dec.seq, dec.buf, 2)
            ok += 1
    return ok
"""


def _stream(seed: int, n_bytes: int) -> bytes:
    """Random bytes with every message kind embedded (extreme field values)."""
    rng = random.Random(seed)
    msgs = []
    for cls in M.MESSAGES.values():
        for pick in (0, 1):
            kw = {f.name: (bytes(f.size) if f.is_raw else f.bounds[pick]) for f in cls.FIELDS}
            msgs.append(cls(**kw))
    msgs += [M.GainsBegin(nbytes=12, crc=M.crc16(bytes(12)), token=3), M.GainsChunk(offset=0, data=bytes(6)),
             M.GainsChunk(offset=6, data=bytes(6)), M.GainsCommit(check=M.table_check(bytes(12))), M.Arm(epoch=3),
             M.Disarm()]
    out = bytearray()
    while len(out) < n_bytes:
        r = rng.random()
        if r < 0.3:
            out += M.encode_serial(rng.choice(msgs), rng.randrange(256))
        elif r < 0.35:  # unknown id with a good CRC
            raw = bytes([rng.choice([0, 20, 31, 200]), 1])
            out += b"\x00" + M.cobs_encode(raw + M.crc16(raw).to_bytes(2, "big")) + b"\x00"
        elif r < 0.4:  # one bit flipped
            f = bytearray(M.encode_serial(rng.choice(msgs), 3))
            f[rng.randrange(1, len(f) - 1)] ^= 1 << rng.randrange(8)
            out += f
        else:
            out += bytes(rng.randrange(256) if rng.random() < 0.8 else 0 for _ in range(rng.randrange(1, 40)))
    return bytes(out) + b"\x00"


@pytest.mark.parametrize("fn", ["feed", "scan"])
def test_unix_decoder_dispatcher_allocation_free_under_heap_lock(fn):
    data = _stream(1, 20000)
    code = _FEED + f"""
import micropython
data = {data!r}
n = len(data)
feed(data[:200], 200)          # warm up: first calls may intern/cache
dec = framing.Decoder(layout)  # fresh counters for the measured run
disp.n_handled = disp.n_refused = sink.n = 0
scan(data[:200], 200)
dec = framing.Decoder(layout)  # fresh counters for the measured run
disp.n_handled = disp.n_refused = sink.n = 0
micropython.heap_lock()
ok = {fn}(data, n)
micropython.heap_unlock()
print(ok, dec.n_crc, dec.n_length, dec.n_unknown, dec.n_overrun, disp.n_handled, disp.n_refused, sink.n)
"""
    out = run_unix(code).split()
    ok, crc, length, unknown, overrun, handled, refused, sent = map(int, out)
    ref = M.SerialStreamDecoder()
    ref.feed(data)
    assert ok == ref.ok and ok > 300
    assert [crc, length, unknown, overrun] == [ref.drops[k] for k in ("crc", "length", "unknown", "overrun")]
    assert min(ref.drops.values()) > 0
    assert handled > 100 and refused > 10 and sent > handled


@pytest.mark.slow
def test_hypothesis_streams_decoded_identically_by_micropython():
    streams: list[bytes] = []
    expected: list[list] = []

    @settings(max_examples=200, deadline=None, suppress_health_check=list(HealthCheck))
    @given(st.lists(st.one_of(st.binary(max_size=30), st.tuples(message_strategy(), st.integers(0, 255))), max_size=10))
    def collect(parts):
        s = b"".join(p if isinstance(p, bytes) else M.encode_serial(*p) for p in parts) + b"\x00"
        streams.append(s)
        host = M.SerialStreamDecoder()
        frames = [(m.ID, q, m.payload().hex()) for m, q in host.feed(s)]
        expected.append([frames, host.drops])
        embedded = [(p[0].ID, p[1], p[0].payload().hex()) for p in parts if not isinstance(p, bytes)]
        it = iter(frames)
        assert all(e in it for e in embedded)

    collect()
    code = """
from firmware import codec, framing
import micropython
layout = codec.Layout()
def run(s):
    dec = framing.Decoder(layout)
    out = []
    for b in s:
        m = dec.feed(b)
        if m >= 0:
            out.append((m, dec.seq, bytes(dec.buf[2:2 + dec.plen])))
    return out, (dec.n_crc, dec.n_length, dec.n_unknown, dec.n_overrun)
def locked(streams):
    dec = framing.Decoder(layout)
    ok = 0
    micropython.heap_lock()
    for s in streams:
        for i in range(len(s)):
            if dec.feed(s[i]) >= 0:
                ok += 1
    micropython.heap_unlock()
    return ok, dec.drops()
""" + f"\nSTREAMS = {streams!r}\nprint(*locked(STREAMS))\nfor s in STREAMS:\n    f, d = run(s)\n    print(repr([(a, b, c.hex()) for a, b, c in f]), d)\n"
    first, *lines = run_unix(code).strip().splitlines()
    # the whole batch once more with the heap locked: same totals, nothing allocated
    assert list(map(int, first.split())) == [sum(len(e[0]) for e in expected), sum(sum(e[1].values()) for e in expected)]
    assert len(lines) == len(streams)
    for line, (frames, drops) in zip(lines, expected):
        f, d = line.rsplit(" (", 1)
        assert eval(f) == [tuple(x) for x in frames]
        assert tuple(int(x) for x in d.rstrip(")").split(",")) == (drops["crc"], drops["length"], drops["unknown"], drops["overrun"])


@pytest.mark.wasm
def test_wasm_32bit_decoder_dispatcher_allocate_nothing():
    data = _stream(2, 6000)
    code = _FEED + f"""
import gc
data = {data!r}
n = len(data)
feed(data, n)
scan(data, n)
ok = ok2 = a1 = 0  # the globals assigned below exist already: no dict growth is measured
gc.collect()
gc.disable()
a0 = gc.mem_alloc()
ok = feed(data, n)
ok2 = scan(data, n)
a1 = gc.mem_alloc()
gc.enable()
print(ok, ok2, a1 - a0, disp.n_handled)
"""
    ok, ok2, delta, handled = map(int, run_wasm(code).split())
    assert ok == ok2 > 100 and handled > 50
    assert delta == 0


def test_wasm_check_is_real():
    # the same measurement sees a bigint: proves the zero above can fail
    if not wasm_available():
        pytest.skip("wasm port not installed")
    out = run_wasm("import gc\ngc.collect()\ngc.disable()\na=gc.mem_alloc()\nx=[0]\nfor i in range(100):\n    x[0] = (1 << 30) + i\nprint(gc.mem_alloc()-a)\n")
    assert int(out) > 0


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["serial", "can"])
def test_micropython_board_on_a_pty(mode):
    br = PtyBridge()
    env = dict(os.environ, MICROPYPATH=f"{ROOT}:.frozen")
    proc = subprocess.Popen([micropython_exe(), str(ROOT / "tests" / "mpy_proto_board.py"), br.b, mode, "60"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env)
    try:
        assert proc.stdout.readline().strip() == "ready"
        if mode == "serial":
            link = L.SerialLink(br.a)
        else:
            link = L.CanLink(interface="serial", channel=br.a, node_id=1)
        kw = {"timeout": 1.0, "retries": 2}
        with link:
            hb = link.query("heartbeat", **kw)
            assert (hb.state, hb.boot, hb.epoch, hb.uptime_ms) == (0, 9, 3, 0xFFFF)
            assert link.query("timing", **kw).values() == (1, 2, 3, 65535)
            assert link.param_set("max_duty", 20000, **kw) == 20000
            with pytest.raises(L.CommandRefused):
                link.param_set("max_duty", 40000, **kw)
            link.upload_gains(bytes(range(100)), **kw)
            link.arm(**kw)
            link.set_reference(0.424242, **kw)
            link.disarm(**kw)
            assert sum(link.drops.values()) == 0
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        br.close()
    assert proc.returncode == 0, err
    words = out.split()
    assert words[0] == "handled" and int(words[1]) >= 20 and words[-3:] == ["424242", "gains", "100"]


def test_fuzz_bench_small_run_agrees_with_host():
    from host.bench.proto import bench_fuzz

    res = bench_fuzz(n_bytes=30000)
    fw, host = res["rows"]
    assert fw["frames_ok"] == host["frames_ok"] > 100
    assert all(fw[k] == host[k] > 0 for k in ("crc", "length", "unknown", "overrun"))


_DISPATCH = standin_source() + """
from firmware import codec, framing, commands

OUT = []
class Sink:
    def write(self, buf, n):
        OUT.append(bytes(buf[:n]).hex())

layout = codec.Layout()
tg = StandIn()
disp = commands.Dispatcher(tg, layout, framing.SerialTx(framing.Encoder(layout), Sink().write))
dec = framing.Decoder(layout)
def run(stream):
    for b in stream:
        m = dec.feed(b)
        if m >= 0:
            r = disp.handle(m, dec.seq, dec.buf, 2)
            OUT.append(str(r))
            if m == T.SET_REFERENCE and r == 0:
                OUT.append('ref %d' % tg.ref)
    OUT.append('state %d %d %d %d' % (tg.state, tg.faults, tg.ref, tg.gsum))
    OUT.append(' '.join(str(v) for v in tg.params))
"""


@pytest.mark.slow
def test_hypothesis_command_sequences_same_replies_in_micropython_and_cpython():
    cmd_classes = [c for c in M.MESSAGES.values() if c.DIRECTION == "to_board"]
    streams: list[bytes] = []

    @settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
    @given(st.lists(st.tuples(st.sampled_from(cmd_classes).flatmap(message_strategy), st.integers(0, 255)), max_size=25))
    def collect(cmds):
        streams.append(b"".join(M.encode_serial(m, s) for m, s in cmds))

    collect()
    body = _DISPATCH + f"STREAMS = {streams!r}\nfor s in STREAMS:\n    run(s)\nprint(chr(10).join(OUT))\n"
    mpy = run_unix(body).strip().splitlines()
    ns: dict = {}
    exec(compile(body.replace("print(chr(10).join(OUT))", ""), "<dispatch>", "exec"), ns)
    assert mpy == ns["OUT"]
    assert sum(1 for line in mpy if line.isdigit() and line != "0") > 20  # refusals happened
