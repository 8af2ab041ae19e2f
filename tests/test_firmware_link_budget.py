"""Bounded link work per tick, under MicroPython (unix port): what the emulated-Pico sweep
(tests/test_link_budget_rp2040.py) measures, checked piece by piece.

* STATS_LOOP never walks the heap in the tick: gc.mem_free/mem_alloc (~9 ms each on a Pico)
  are sampled between ticks while the motor is off, and the reply reports the last sample;
* SerialLink dispatches at most _FRAMES frames a tick; the rest wait, in order, and are counted
  (status values link_deferred, link_wait_max);
* a gain commit while armed is refused (ARMED) before any CRC work -- even for a table whose CRC
  is wrong -- and the upload is kept (until the session ends); the CRCs are built chunk by chunk;
* param_set of what would tip a balancing robot (msgtable.DRIVE_PARAMS) is refused (ARMED) while
  armed or balancing, accepted once disarmed; harmless parameters are accepted.
"""

from __future__ import annotations

import pytest

from firmware import msgtable as T
import fwharness as H
from host.boards.mpyrun import run_unix

SCRIPT = H.FAKE_HAL + """
from array import array
import firmware.appstatus as A  # the heap sample (Reports.sample_heap) lives there
from firmware import codec, crc16, framing
from firmware import msgtable as T
from firmware.app import App
from firmware.link_serial import SerialLink, FRAMES_PER_TICK as _FRAMES

calls = [0]
real_free = A._mem_free
def counted():
    calls[0] += 1
    return real_free() if real_free is not None else 0
A._mem_free = counted

layout = codec.Layout()
table = crc16.make_table()
enc = framing.Encoder(layout, table)
vals = array('i', [0] * 8)

class Uart:
    # bytes written to the board wait here; what the board writes is decoded
    def __init__(s):
        s.inb = bytearray()
        s.dec = framing.Decoder(layout, table)
        s.got = []
    def put(s, mid, seq, *v):
        for i in range(len(v)):
            vals[i] = v[i]
        n = enc.encode(mid, seq, vals, 0)
        s.inb += enc.out[:n]
    def any(s):
        return len(s.inb)
    def readinto(s, buf, n):
        n = min(n, len(s.inb))
        buf[:n] = s.inb[:n]
        s.inb = s.inb[n:]
        return n
    def write(s, b):
        for x in bytes(b):
            m = s.dec.feed(x)
            if m >= 0:
                s.got.append((m, s.dec.seq, bytes(s.dec.buf[2:2 + s.dec.plen])))

hal = Hal()
hal.inc = 10
uart = Uart()
app = App(hal, config={'watchdog_ms': 0, 'stall_ms': 0, 'epoch': 0, 'telem_div': 0, 'heartbeat_ms': 0})
link = SerialLink(uart, app)
app.set_link(link)
app.step()

# --- stats: no heap walk in the tick ---
calls[0] = 0
uart.put(T.REQUEST, 1, T.STATS_DECODE)
app.step(); link.poll()
print('stats_frames', sum(1 for m in uart.got if m[0] == T.STATS_LOOP))
print('heap_walks_in_tick', calls[0])
app.run(n=2, lock=False)  # disarmed: sampled between ticks
print('heap_walks_between', calls[0])

# --- frames per tick ---
uart.got.clear()
for i in range(12):
    uart.put(T.PARAM_GET, 10 + i, i % T.N_PARAMS)
per = []
for k in range(8):
    n0 = len(uart.got)
    app.step(); link.poll()
    per.append(len(uart.got) - n0)
print('per_tick', ' '.join(str(x) for x in per))
print('order', ' '.join(str(m[1]) for m in uart.got))
print('deferred', app.status_get(T.S_LINK_DEFERRED), 'wait_max', app.status_get(T.S_LINK_WAIT_MAX), 'frames_max', _FRAMES)

# --- balancing: drive params refused, harmless accepted; commit refused before the CRC ---
hal.adc = 2048
print('arm', app.cmd_arm())
app.run(n=40, lock=False)  # the warm-up periods, then balancing
print('state', app.sup.state)
def pset(i, v):
    return app.param_set(i, v)
for i in T.DRIVE_PARAMS:
    lo = [p for p in T.PARAMS if p[0] == i][0]
    v = lo[4] if app.params[i] != lo[4] else lo[3]
    print('drive', i, pset(i, v), app.params[i] != v)
print('harmless', pset(T.P_TELEM_DIV, 7), app.params[T.P_TELEM_DIV])
d = link.disp
blob = bytearray(64)
for i in range(64):
    blob[i] = (i * 7) & 0xFF
print('begin', d._gains_begin(len(blob), 0x1234, 1))   # a CRC that does not match
for off in range(0, len(blob), 6):
    buf = bytearray(12)
    n = min(6, len(blob) - off)
    buf[2:2 + n] = blob[off:off + n]
    d._gains_chunk(off, buf, 2, 2)
print('commit_armed', d._gains_commit(3, 0), d.g_active)
print('run_crc', d.g_run == crc16.compute(table, blob, 0, len(blob)))
print('disarm', app.cmd_disarm())
for i in T.DRIVE_PARAMS:
    lo = [p for p in T.PARAMS if p[0] == i][0]
    print('drive_off', i, pset(i, lo[5] if lo[5] >= lo[3] else lo[3]))
print('commit_disarmed', d._gains_commit(4, 0))
"""


@pytest.fixture(scope="module")
def out() -> dict[str, list[str]]:
    res: dict[str, list[str]] = {}
    for line in run_unix(SCRIPT, timeout=60).splitlines():
        if line.strip():
            k, *v = line.split()
            res.setdefault(k, []).append(" ".join(v))
    return res


def test_stats_reply_walks_no_heap_in_the_tick(out) -> None:
    assert out["stats_frames"] == ["1"]
    assert out["heap_walks_in_tick"] == ["0"]
    assert int(out["heap_walks_between"][0]) >= 1  # sampled by run() with the motor off


def test_frames_beyond_the_budget_wait_in_order_and_are_counted(out) -> None:
    per = [int(x) for x in out["per_tick"][0].split()]
    deferred, _, wait_max, _, fmax = out["deferred"][0].split()
    assert sum(per) == 12 and max(per) <= int(fmax) < 12, per
    assert [int(s) for s in out["order"][0].split()] == list(range(10, 22))  # nothing lost or reordered
    assert int(deferred) >= 12 - per[0] and int(wait_max) >= 2, out["deferred"]


def test_drive_params_refused_while_balancing(out) -> None:
    assert out["arm"] == [str(T.OK)] and out["state"] == ["2"]
    drive = {int(r.split()[0]): r.split()[1:] for r in out["drive"]}
    assert set(drive) == set(T.DRIVE_PARAMS)
    for i, (r, unchanged) in drive.items():
        assert int(r) == T.R_ARMED and unchanged == "True", (i, r)
    assert out["harmless"] == [f"{T.OK} 7"]
    assert all(int(r.split()[1]) == T.OK for r in out["drive_off"])


def test_commit_while_armed_refused_before_the_crc(out) -> None:
    # the table's CRC is wrong: ARMED (not BAD_CRC) says the state was checked first, and the
    # upload is kept -- until the disarm ends its session (a new arming token)
    assert out["begin"] == [str(T.OK)]
    assert out["commit_armed"] == [f"{T.R_ARMED} True"]
    assert out["run_crc"] == ["True"]
    assert out["commit_disarmed"] == [str(T.R_STALE_EPOCH)]
