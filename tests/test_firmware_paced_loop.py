"""The board's paced loop -- App.run() with the UART link -- allocates nothing, per tick.

What a board runs every tick: the busy-wait on the HAL clock, the control step, the
link's poll (bytes from the UART, command dispatch, telemetry every tick, heartbeats) --
over 2000 ticks with the HAL clock crossing its 2**30 wrap, and the tick and uptime
counters crossing theirs.  A scripted UART releases command frames at given ticks
(telemetry divider, arm, reference, keep-alives, a burst of requests larger than one
tick's read, a watchdog fault, clear and re-arm) and decodes what the board writes.

* WebAssembly port (32-bit: small ints are 31-bit as on the RP2040): ``gc.mem_alloc()``
  delta with ``gc.disable()`` and ``App.run(n, lock=False)`` (a heap lock misbehaves on
  that port) -- a big int anywhere (e.g. ``2**30`` in a tick wrap) shows here;
* unix port: ``App.run(n)`` exactly as on the board, i.e. under its own
  ``micropython.heap_lock()``: an allocation would latch F_LOOP.  A control run whose
  link allocates shows that the lock is real and that it ends as a fault with the motor
  off, not as a crash.

Also checked: the link reads only the bytes ``any()`` reports (rp2's ``readinto(buf, n)``
waits for n bytes), at most 64 per tick.
"""

from __future__ import annotations

import pytest

from firmware import msgtable as T
from firmware.supervisor import F_LOOP, F_WATCHDOG
import fwharness as H
from host.boards.mpyrun import run_unix, run_wasm

N_TICKS = 2000

SCRIPT = H.host_frames_src(8192, 400) + """
import gc
from firmware import gains
from firmware import msgtable as T
from firmware.app import App
from firmware.crc32 import of as crc32_of
from firmware.link_serial import SerialLink
from firmware.hal_base import Hal as HalBase

_MASK = 0x3FFFFFFF


class Hal(HalBase):
    # not fwharness.FAKE_HAL: sensors that change every tick and a clock that crosses its wrap
    # scripted sensors; the clock advances `inc` us per read and starts 1.5 s before
    # its 2**30 wrap (wrapped here without ever computing 2**30)
    def __init__(s):
        s.n = 0
        s.duty = 0
        s.t = _MASK - 1500000
        s.inc = 250

    def read_angle_raw(s):
        s.n += 1
        return 2048 + (s.n % 11) - 5

    def read_encoder(s):
        return (65530 + (s.n % 9)) & 0xFFFF

    def set_motor(s, d):
        s.duty = d

    def ticks_us(s):
        t = s.t
        if t > _MASK - s.inc:
            s.t = t - (_MASK - s.inc) - 1
        else:
            s.t = t + s.inc
        return s.t


add(60, T.PARAM_SET, T.P_TELEM_DIV, 1)
class _Tok:
    epoch = 0
def token(k):
    # the arming token after k draws from 0 (config epoch 0; App._new_token: a fault, a clear)
    t = _Tok()
    for _ in range(k):
        App._new_token(t)
    return t.epoch
add(61, T.ARM, token(0))  # the arming token: 0 at start (config), drawn anew by the watchdog fault and by clear
add(63, T.SET_REFERENCE, 50000)
for k in range(100, 1500, 40):
    add(k, T.REQUEST, T.HEARTBEAT)
    add(k, T.HOST_HEARTBEAT)  # keep-alives: the watchdog is fed (requests alone do not)
for i in range(12):
    add(700, T.PARAM_GET, i % T.N_PARAMS)  # one burst: more than a tick's read
add(900, T.REQUEST, T.TIMING)
# quiet from 1500: the watchdog (250 ms = 125 ticks) cuts the motor; with the motor off,
# the gain table is uploaded again (all frames at once: read 64 bytes a tick); then
# clear, re-arm
FL = gains.FLAT
NB = 4 * len(FL)
BLOB = bytearray(NB + 6)
for i in range(len(FL)):
    for j in range(4):
        BLOB[4 * i + j] = (FL[i] >> (8 * j)) & 0xFF
add(1700, T.GAINS_BEGIN, NB, crc16.compute(table, BLOB, 0, NB), token(1))
NCHUNK = 0
for off in range(0, NB, T.CHUNK_BYTES):
    enc.raw[4:4 + T.CHUNK_BYTES] = BLOB[off:off + T.CHUNK_BYTES]
    add(1700, T.GAINS_CHUNK, off)
    NCHUNK += 1
add(1700, T.GAINS_COMMIT, crc32_of(BLOB, NB))
add(1800, T.CLEAR_FAULTS)
add(1801, T.ARM, token(2))
for k in range(1810, 2050, 40):
    add(k, T.REQUEST, T.HEARTBEAT)
    add(k, T.HOST_HEARTBEAT)


class FakeUart(HostEnd):
    # machine.UART's surface: any() = bytes waiting, readinto(buf, n), write(buf); a frame is
    # released at its tick (REL) of the HAL's step count
    def __init__(s, hal):
        HostEnd.__init__(s)
        s.hal = hal
        s.over = 0  # readinto asked for more than any() said: a blocking read on rp2
        s.maxreq = 0

    def any(s):
        f = s.frame
        end = s.rd
        while f < NF and REL[f] <= s.hal.n:
            end = END[f]
            f += 1
        return end - s.rd

    def readinto(s, buf, n):
        a = s.any()
        if n > a:
            s.over += 1
        if n > s.maxreq:
            s.maxreq = n
        return s.give(buf, n if n < a else a)


hal = Hal()
app = App(hal, config={'stall_ms': 0, 'epoch': 0})
uart = FakeUart(hal)
app.set_link(SerialLink(uart, app))
app.run(50, LOCK)  # warm-up, before any frame
# the tick and uptime counters cross their 2**30 wrap during the measured run
app.tick = _MASK - 700
app.uptime_ms = _MASK - 1500
gc.collect()
gc.disable()
a0 = gc.mem_alloc()
app.run(N_TICKS, LOCK)
a1 = gc.mem_alloc()
gc.enable()
print('alloc', a1 - a0)
print('steps', hal.n)
print('tick', app.tick)
print('uptime', app.uptime_ms)
print('clock', hal.t)
print('state', app.sup.state)
print('faults', app.sup.faults)
print('over', uart.over)
print('maxreq', uart.maxreq)
print('unread', NF - uart.frame)
uart.report()
print('drops', uart.dec.drops())
print('ref', app.ref_um)
print('nchunk', NCHUNK)
"""

# unix port: the same link, but a poll that allocates: App.run's heap lock turns it into
# a latched F_LOOP fault with the motor off, the loop keeps its pace, the heap is
# unlocked afterwards
ALLOC_CONTROL = """
class Leaky:
    def __init__(s, link):
        s.link = link
        s.bad = 0
    def poll(s):
        s.link.poll()
        if hal.n == 1500:
            s.bad = [hal.n]  # an allocation in the loop
app2 = App(hal, config={'stall_ms': 0, 'watchdog_ms': 0})
app2.set_link(Leaky(SerialLink(FakeUart(hal), app2)))
hal.n = 1400
app2.cmd_arm()
app2.run(200)
print('ctl_steps', hal.n - 1400)
print('ctl_state', app2.sup.state)
print('ctl_faults', app2.sup.faults)
print('ctl_duty', hal.duty)
x = [1, 2, 3]  # the heap is usable again
print('ctl_unlocked', len(x))
"""


_obs = H.parse_ints


def _script(lock: bool, control: str = "") -> str:
    return SCRIPT.replace("LOCK", "True" if lock else "False").replace("N_TICKS", str(N_TICKS)) + control


def _check_run(obs: dict[str, int]) -> None:
    assert obs["steps"] == 50 + N_TICKS
    # every counter crossed its wrap and came out small and in range
    assert obs["tick"] == N_TICKS - 701
    assert 0 <= obs["uptime"] < 4000 and 0 <= obs["clock"] < 2**30
    # the link read only what was there, at most 64 bytes a tick, and lost nothing
    assert obs["over"] == 0 and 0 < obs["maxreq"] <= 64
    assert obs["unread"] == 0 and obs["drops"] == 0
    # commands obeyed; the quiet spell fired the watchdog; cleared and re-armed
    assert obs["ref"] == 50000
    assert obs["param_value"] == 13 and obs["timing"] == 1 and obs["nack"] == 0
    assert obs["ack"] == 4 + obs["nchunk"] + 2  # arm, reference, clear, arm; the upload
    assert obs["state"] == 2 and obs["faults"] == 0
    # telemetry every tick from tick 60 on; heartbeats: requested + every 100 ms (50 ticks)
    assert N_TICKS - 20 <= obs["telem_state"] == obs["telem_ctrl"] <= N_TICKS
    periodic = obs["heartbeat"] - (len(range(100, 1500, 40)) + len(range(1810, 2050, 40)))
    assert abs(periodic - (50 + N_TICKS) // 50) <= 2, obs


@pytest.mark.slow
@pytest.mark.wasm
def test_paced_loop_with_link_allocates_nothing_32bit_wasm() -> None:
    obs = _obs(run_wasm(_script(lock=False), timeout=600))
    assert obs["alloc"] == 0, f"{obs['alloc']} bytes over {N_TICKS} ticks"
    _check_run(obs)


@pytest.mark.slow
def test_paced_loop_with_link_under_its_own_heap_lock_unix() -> None:
    obs = _obs(run_unix(_script(lock=True, control=ALLOC_CONTROL), timeout=300))
    assert obs["alloc"] == 0
    _check_run(obs)  # faults == 0: no F_LOOP, nothing allocated under the lock
    # the control: an allocation in the loop is a latched fault with the motor off
    assert obs["ctl_steps"] == 200
    assert obs["ctl_state"] == 3 and obs["ctl_faults"] == F_LOOP and obs["ctl_duty"] == 0
    assert obs["ctl_unlocked"] == 3


def test_loop_fault_is_a_flag_of_its_own_in_the_low_byte() -> None:
    # HIL_ACTUATOR carries the low 8 fault bits
    from firmware import supervisor as S

    flags = [v for k, v in vars(S).items() if k.startswith("F_")]
    assert F_LOOP < 0x100 and flags.count(F_LOOP) == 1 and F_LOOP & F_WATCHDOG == 0


# ---- CPython: the pieces, one behaviour each ----

class _Hal(H.StandInHal):
    # counts its ADC reads (one per control step)
    def __init__(self) -> None:
        super().__init__(inc=500)
        self.n = 0

    def read_angle_raw(self) -> int:
        self.n += 1
        return self.adc


class _Disp:
    def __init__(self) -> None:
        self.sent: list[tuple[str, int, int]] = []
        self.tick = 0

    def send_telemetry(self, seq: int) -> None:
        self.sent.append(("tel", seq, self.tick))

    def send_heartbeat(self, seq: int) -> None:
        self.sent.append(("hb", seq, self.tick))


class _App:
    def __init__(self, div: int, hb_ms: int, period_us: int) -> None:
        self.p = {T.P_TELEM_DIV: div, T.P_HEARTBEAT_MS: hb_ms}
        self.period_us = period_us

    def param_get(self, i: int) -> int:
        return self.p[i]


def _pace(div: int, hb_ms: int, period_us: int, ticks: int) -> list[tuple[str, int, int]]:
    from firmware.pacer import Pacer

    d = _Disp()
    p = Pacer(_App(div, hb_ms, period_us), d)
    for k in range(1, ticks + 1):
        d.tick = k
        p.tick()
    return d.sent


@pytest.mark.parametrize("period_us", [2000, 1000, 20000, 500])
def test_pacer_counts_board_time(period_us: int) -> None:
    sent = _pace(10, 100, period_us, 1000)
    tel = [k for w, _, k in sent if w == "tel"]
    hb = [k for w, _, k in sent if w == "hb"]
    assert tel == list(range(1, 1001, 10))
    every = -(-100000 // period_us)  # heartbeat_ms in ticks at this rate (at least one)
    # due with the first telemetry: the heartbeat goes on the next tick (no tick carries
    # both), then every heartbeat_ms from there (these rates never meet a telemetry tick again)
    assert hb == list(range(2, 1001, every))
    assert not set(tel) & set(hb)
    # one sequence for both, in send order, wrapping at 8 bits
    assert [s for _, s, _ in sent] == [(i + 1) & 0xFF for i in range(len(sent))]


def test_pacer_off_switches_and_idle_time() -> None:
    assert _pace(0, 0, 2000, 500) == []
    assert {w for w, _, _ in _pace(0, 100, 2000, 500)} == {"hb"}
    from firmware.pacer import Pacer

    d = _Disp()
    p = Pacer(_App(10, 100, 2000), d)
    p.elapse(50000)  # a HIL lockstep link with no ticks: the first wait says hello at once
    for _ in range(4):
        p.elapse(50000)
    assert [w for w, _, _ in d.sent] == ["hb", "hb", "hb"]


class _ByteUart:
    # any() may under-report (1 when more waits, as the docs allow); a read of more than
    # is waiting is an error here (rp2 would wait for it)
    def __init__(self, data: bytes, any_one: bool = False) -> None:
        self.data = bytearray(data)
        self.any_one = any_one
        self.requests: list[int] = []
        self.out = bytearray()

    def any(self) -> int:
        n = len(self.data)
        return min(n, 1) if self.any_one else n

    def readinto(self, buf, n):
        if n > len(self.data):
            raise AssertionError("would block: more asked than waiting")
        self.requests.append(n)
        if n == 0:
            return None
        buf[:n] = self.data[:n]
        del self.data[:n]
        return n

    def write(self, mv) -> int:
        self.out += bytes(mv)
        return len(mv)


def _frames(n: int) -> bytes:
    from firmware import codec, crc16, framing

    enc = framing.Encoder(codec.Layout(), crc16.make_table())
    vals = [T.P_WATCHDOG_MS, 0, 0, 0]
    out = b""
    for i in range(n):
        k = enc.encode(T.PARAM_GET, i, vals, 0)
        out += bytes(enc.out[:k])
    return out


@pytest.mark.parametrize("any_one", [False, True])
def test_link_reads_what_is_waiting_bounded_per_tick(any_one: bool) -> None:
    from firmware import codec, crc16, framing
    from firmware.app import App
    from firmware.link_serial import SerialLink

    data = _frames(30)  # a burst of 30 requests, far more than a tick's read
    uart = _ByteUart(data, any_one)
    app = App(_Hal(), config={"watchdog_ms": 0, "telem_div": 0, "heartbeat_ms": 0})
    from firmware.link_serial import FRAMES_PER_TICK

    link = SerialLink(uart, app)
    # the time budget off (this fake clock moves 500 us a read; the budget is measured on the
    # emulated Pico, tests/test_link_budget_rp2040.py): frames and bytes per tick only
    link._budget = False
    dec = framing.Decoder(codec.Layout(), crc16.make_table())
    ticks = 0
    per_tick = []
    while (uart.data or link._ri < link._rn or link._pend >= 0) and ticks < 100:
        n0 = len(uart.out)
        link.poll()
        per_tick.append([dec.feed(b) for b in uart.out[n0:]].count(T.PARAM_VALUE))
        ticks += 1
    # bounded work per tick: at most FRAMES_PER_TICK frames dispatched, at most 64 bytes a read
    # (whatever any() says); the rest waits for the next tick, nothing lost
    assert max(per_tick) <= FRAMES_PER_TICK and ticks >= -(-30 // FRAMES_PER_TICK), per_tick
    assert max(uart.requests) <= 64
    assert sum(per_tick) == 30


def test_a_memory_error_in_the_loop_is_a_fault_not_a_crash() -> None:
    from firmware.app import App
    from firmware.supervisor import FAULT

    hal = _Hal()
    app = App(hal, config={"watchdog_ms": 0, "stall_ms": 0})

    class Poll:
        def poll(self) -> None:
            if hal.n == 30:
                raise MemoryError

    app.set_link(Poll())
    app.cmd_arm()
    app.run(60)
    assert hal.n == 60  # paced on
    assert app.sup.state == FAULT and app.sup.faults == F_LOOP and hal.duty == 0


@pytest.mark.parametrize("t0", [0, (1 << 30) - 3000, 7 << 30, (1 << 62) - 3000])
def test_run_paces_one_step_a_period_on_any_clock(t0: int) -> None:
    # App.run on a HAL clock near its wrap, or from a port whose ticks period is a larger
    # multiple of 2**30 (the unix port: 2**62): one step every period, no burst, no stall
    from firmware.app import App

    hal = _Hal()
    hal.t = t0
    starts: list[int] = []


    def ticks() -> int:
        hal.t += 100
        return hal.t

    hal.ticks_us = ticks
    app = App(hal, config={"watchdog_ms": 0, "stall_ms": 0})

    class Rec:
        def poll(self) -> None:
            starts.append(app.timing.last_us)

    app.set_link(Rec())
    app.run(50)
    # last_us is the raw HAL value; the fake clock moves 100 us a read
    gaps = [b - a for a, b in zip(starts, starts[1:])]
    assert all(abs(g - app.period_us) <= 100 for g in gaps), gaps
    assert abs(starts[-1] - starts[0] - 49 * app.period_us) <= 100
