"""The CAN link's admission rule in predicted time (firmware/admit.py via link_can.CanLink), under
MicroPython (unix port) with a scripted MCP2515 and a clock the test sets.

The rule is measured on the emulated Pico (tests/test_rp2040_can_hil.py); here it is checked
piece by piece, at given times into the tick (``AT`` us after the step's start, period 2000 us,
a host heartbeat planned at 400 + 400 (CAN) + 3 x 100 (SPI loads) = 1100 us):

* a frame just read that ends within the period is dispatched in its tick;
* one that would not is held -- read from the chip once, dispatched once, in the next tick (its
  limit there App.link_budget_us), nothing else read from the chip before it goes;
* while a frame is held the chip's flags are still read: a bus-off latches F_CAN in its tick and
  drops the held command;
* a frame that never fits goes after 8 held ticks (admit.FORCE) whatever the time.

One MicroPython process for the module: about 10-15 s.
"""

from __future__ import annotations

import pytest

import fwharness as H
from host.boards.mpyrun import run_unix

pytestmark = pytest.mark.slow

SCRIPT = H.FAKE_HAL + """
from firmware import msgtable as T
from firmware.app import App
from firmware.link_can import CanLink
from firmware.supervisor import F_CAN
from firmware import mcp2515 as C

class Drv:
    # the MCP2515 driver's interface (firmware/mcp2515.py), scripted: frames waiting in RXB0/RXB1
    def __init__(s):
        s.rx = []  # (rid, dlc, data) in arrival order
        s.eflg = 0
        s.intf = 0
        s.err = 0
        s.rid = 0
        s.rdlc = 0
        s.rdata = bytearray(8)
        s.tec = 0
        s.rec = 0
        s.reads = 0
        s.nflags = 0
    def init(s, bitrate, xtal, node):
        return C.OK
    def pending(s):
        return bool(s.rx) or s.err
    def flags(s):
        s.nflags += 1
        s.intf = (1 if len(s.rx) > 0 else 0) | (2 if len(s.rx) > 1 else 0) | (0x20 if s.err else 0)
        s.eflg = s.err
    def read_rx(s, k):
        s.reads += 1
        rid, dlc, d = s.rx.pop(0)
        s.rid = rid
        s.rdlc = dlc
        for i in range(8):
            s.rdata[i] = d[i] if i < len(d) else 0
    def counters(s):
        pass
    def clear_errors(s):
        pass
    def abort(s):
        pass
    def tx_busy(s):
        return 0
    def load_frame(s, k, q):
        pass
    def rts(s, m):
        pass

hal = Hal()
hal.inc = 0  # the clock moves only when the test sets it
app = App(hal, config={'stall_ms': 0, 'telem_div': 0, 'heartbeat_ms': 0, 'watchdog_ms': 0})
drv = Drv()
ln = CanLink(drv, app)
got = []
real = ln.disp.handle
def handle(mid, seq, buf, off):
    got.append((tick[0], mid))
    real(mid, seq, buf, off)
ln.disp.handle = handle
tick = [0]
HB = ((ln.node & 0x3F) << 5) | T.HOST_HEARTBEAT

def one(at):
    # a tick: the step at its scheduled start, the link's poll `at` us into it
    tick[0] += 1
    hal.t = tick[0] * 2000
    app.step()
    hal.t = tick[0] * 2000 + at
    ln.poll()

print('period', app.period_us, 'budget', app.link_budget_us)
one(500)
drv.rx.append((HB, 0, b''))
one(500)
print('fits', got, drv.reads)
got.clear()
drv.rx.append((HB, 0, b''))
drv.rx.append((HB, 0, b''))
one(1500)
print('held', got, drv.reads, ln._pend)
one(500)
print('next', got, drv.reads, ln._pend)
one(500)
print('after', got, drv.reads, len(drv.rx))
got.clear()
# held, then bus-off in the next tick (still not fitting)
drv.rx.append((HB, 0, b''))
one(1500)
n0 = drv.nflags
drv.err = C.TXBO
one(2600)
print('busoff', got, ln._pend, app.sup.faults & F_CAN, ln.bus_off, drv.nflags - n0)
drv.err = 0
one(500)
ln.bus_off = False
app.sup.faults = 0
got.clear()
# never fits: forced after FORCE held ticks
drv.rx.append((HB, 0, b''))
for i in range(12):
    one(2700)
print('forced', got, tick[0])
"""


@pytest.fixture(scope="module")
def out() -> dict[str, str]:
    text = run_unix(SCRIPT, timeout=120)
    return {ln.split(" ", 1)[0]: ln.split(" ", 1)[1] for ln in text.splitlines() if " " in ln}


def test_the_test_runs_at_500_hz(out) -> None:
    assert out["period"] == "2000 budget 2500", out


def test_a_frame_that_fits_goes_in_its_tick(out) -> None:
    assert out["fits"] == "[(2, 20)] 1", out


def test_a_frame_that_does_not_fit_is_held_in_the_driver_and_goes_next_tick(out) -> None:
    # tick 3: read (one of two in the chip), held; the second stays in the chip
    assert out["held"] == "[] 2 20", out
    # tick 4: the held one goes first (500 + 1100 <= 2500), then the chip's other one (read now,
    # the fake clock still at 500: 500 + 1100 <= 2000)
    assert out["next"] == "[(4, 20), (4, 20)] 3 -1", out
    assert out["after"].endswith(" 3 0") and out["after"].count("20)") == 2, out


def test_a_held_frame_does_not_hide_a_bus_off(out) -> None:
    # the flags were read in the tick with the held frame: F_CAN latched there, the command dropped
    got, pend, fcan, bus_off, nflags = out["busoff"].rsplit(" ", 4)
    assert got == "[]" and pend == "-1" and int(fcan) != 0 and bus_off == "True" and int(nflags) >= 1, out


def test_a_frame_that_never_fits_is_forced_after_eight_ticks(out) -> None:
    got = out["forced"].rsplit(" ", 1)[0]
    # read on the first tick, held 8 ticks (admit.FORCE), then goes: exactly once
    assert got.count(", 20)") == 1, out
    t0 = int(out["forced"].rsplit(" ", 1)[1]) - 11  # the tick it was read
    assert got == f"[({t0 + 8}, 20)]" or got == f"[({t0 + 9}, 20)]", out
