"""The driver-enable dead-man on the emulated board (issue 23 item 2), measured on the pins.

HalPico drives EN through a PIO state machine (firmware/hal_pico.py ``_deadman``, PIO1) that holds
it low unless the loop refreshes it: every ``set_motor`` while the driver is enabled puts one word
into its TX FIFO, and the machine cuts EN ``board.DEADMAN_PCT`` (175) % of the loop period after
the last one -- whatever the CPU is doing.  A hang is injected at four points of a balancing loop
(App.run with the board's own config: viper, heap locked, hardware watchdog on):

* ``step``: in the control step, right after a non-zero duty went out (a Python ``while True``);
* ``poll``: in the link poll, a UART write that blocks in C for 20 s;
* ``hal``: in a HAL call, the encoder read waiting in C (``sm.get()``) on a stopped state machine;
* ``irq_off``: in the step, interrupts disabled and a loop that never yields.

Each time EN falls 3.5 ms after the last motor command on the pins (the last PWM compare write:
the refresh follows it by a few instructions), within three periods of the last complete tick and
of the hang; the PWM is never written again, and the hardware watchdog (board.WDT_MS) still resets
the board about 100 ms after the hang -- its pins back to inputs, RC_WATCHDOG at the next boot.
The timeout follows the loop period (50-2000 Hz tables); a balancing loop with telemetry every
tick never trips it, and the refresh costs under a microsecond a tick.

Measured here (125 MHz emulated cycles): EN low 3.51-3.52 ms after the last refresh for every hang
point (<= 5.52 ms after the tick before it, 1.9-3.5 ms after the hang itself), reset 98-98.4 ms
after the hang; the refresh 0.70 us a tick.  One board for the module (each hang ends in a
watchdog reset; the test re-enters the REPL of the rebooted board): about 60-70 s of wall time.
"""

from __future__ import annotations

import pytest

from firmware import board as BOARD
from firmware import msgtable as T
import fwharness as H
from host.boards.rp2040.board import EmulatedBoard

pytestmark = pytest.mark.rp2040  # slow; skipped without the emulated board (tests/conftest.py)

US = 125  # cycles per microsecond
PERIOD_US = 2000  # the shipped table's 500 Hz
# the dead-man's timeout from a refresh: N + 1 loops of 16 us, N = DEADMAN_PCT % of the period / 16 - 1
TIMEOUT_US = (BOARD.DEADMAN_PCT * PERIOD_US) // (100 * 16) * 16  # 3488 us
MARK = 25  # a spare pin (the LED) the injected code raises at the moment it hangs
AT = 150  # the tick (of non-zero duty) the hang comes in: balancing for 0.3 s first

# the board's own App config (viper, hardware watchdog), with the host's command watchdog and
# the no-motion check off: no host and no plant here, a tilted pendulum the controller pushes
SETUP = """
import machine, time
import firmware.board as B
from firmware.hal_pico import HalPico
from firmware.app import App
hal = HalPico(B)
led = machine.Pin(25, machine.Pin.OUT, value=0)
cfg = B.config()
cfg['watchdog_ms'] = 0
cfg['stall_ms'] = 0
app = App(hal, config=cfg)
N = [0]
motor = app._set_motor
enc = app._read_enc
U = machine.UART(1, 9600, tx=machine.Pin(4), rx=machine.Pin(5))
BIG = bytes(4000)  # 4 s of line: a hang far past the watchdog (20 kB no longer fits in one piece beside the App)


HANG = 0  # at the AT-th non-zero duty m_motor: 0 goes on, 1 hangs, 2 hangs with interrupts off


def m_motor(d):
    # the motor command, the non-zero ones counted (N)
    motor(d)
    if d:
        N[0] += 1
        if HANG and N[0] == AT:
            led.value(1)
            if HANG == 2:
                machine.disable_irq()
            while True:
                pass


def e_hal():
    if N[0] == AT:
        led.value(1)
        hal._sm.active(0)
        HalPico.read_encoder(hal)  # the portable read: sm.get() on a stopped machine never returns
    return enc()


class Stuck:
    def poll(s):
        if N[0] == AT:
            led.value(1)
            U.write(BIG)  # 4 s of line at 9600 baud: blocks in C
"""

INJECT = {
    "step": "HANG = 1\napp._set_motor = m_motor\n",
    "poll": "app._set_motor = m_motor\napp.set_link(Stuck())\n",
    "hal": "app._set_motor = m_motor\napp._read_enc = e_hal\n",
    "irq_off": "HANG = 2\napp._set_motor = m_motor\n",
}


@pytest.fixture(scope="module")
def board():
    with EmulatedBoard(main=False) as b:
        b._request({"cmd": "config", "watch": [BOARD.DIR_PIN, BOARD.EN_PIN, MARK]})
        b.set_adc(2048 + 30)  # a little off upright: the controller drives the motor
        yield b


def test_refresh_costs_microseconds_per_tick(board: EmulatedBoard) -> None:
    # hal.set_motor with the driver disabled (no refresh) and enabled (the refresh: the IRQ flag
    # looked at, one FIFO word), 1000 calls each, the same loop around them
    board.exec(SETUP, timeout=5.0)
    code = ("t = time.ticks_us\nr = []\nfor on in (0, 1, 0, 1):\n    hal.set_enable(on)\n    t0 = t()\n"
            "    for i in range(1000):\n        hal.set_motor(1000)\n    r.append(time.ticks_diff(t(), t0))\n"
            "hal.set_enable(0)\nprint(*r)")
    off0, on0, off1, on1 = (int(v) for v in board.exec(code, timeout=10.0).split())
    per_call = ((on0 + on1) - (off0 + off1)) / 2000
    print(f"\nset_motor x1000: off {off0}/{off1} us, on {on0}/{on1} us -> refresh {per_call:.2f} us a tick")
    assert 0.0 < per_call < 5.0, (off0, on0, off1, on1)


@pytest.mark.parametrize("period", [500, 4000, 20000])
def test_timeout_follows_the_loop_period(board: EmulatedBoard, period: int) -> None:
    # the loop rates a table may have (50-2000 Hz): one motor command, then nothing -- EN is one
    # pulse of DEADMAN_PCT % of the period, counted from that command
    board.exec(f"import firmware.board as B\nfrom firmware.hal_pico import HalPico\nhal = HalPico(B)\n"
               f"hal.set_period({period})", timeout=3.0)
    board.usb_write(b"hal.set_enable(1)\nhal.set_motor(1000)\n\x04")
    edges, ev, _, _ = H.collect_pins(board, 20 + 2 * period // 1000,
                               until=lambda e, r: any(p == BOARD.EN_PIN and v == 0 for p, _, v in e))
    board._read_until(b"\x04", 1e6)
    en = [(c, v) for p, c, v in edges if p == BOARD.EN_PIN]
    assert [v for _, v in en] == [1, 0], en
    last = max(c for c, *_ in ev if c < en[1][0])
    want = (BOARD.DEADMAN_PCT * period) // (100 * 16) * 16
    assert want <= (en[1][0] - last) / US < want + 50, ((en[1][0] - last) / US, want)
    board.exec("hal.set_enable(0)", timeout=2.0)


def test_balancing_loop_never_trips_it(board: EmulatedBoard) -> None:
    # the shipped loop with its UART link, telemetry every tick (the link's worst case): the
    # refresh comes every period (EN high throughout), no expiry counted; once the bounded run
    # ends the loop is gone and EN falls two periods after the last refresh
    board.exec(SETUP + "from firmware.link_serial import SerialLink\ncfg['telem_div'] = 1\napp = App(hal, config=cfg)\n"
               "app.set_link(SerialLink(hal.uart(), app))\n", timeout=5.0)
    board.usb_write(b"app.sup.arm()\napp.run(600)\nprint('done', app.sup.state, app.sup.faults, app.n_late, "
                    b"hal.deadman_trips())\n\x04")
    edges, ev, _, _ = H.collect_pins(board, 1400, until=lambda e, r: any(p == BOARD.EN_PIN and v == 0 for p, _, v in e))
    out = board._read_until(b"\x04", 3e6).decode()
    state, faults, late, trips = (int(v) for v in out.split("done")[1].split()[:4])
    assert state == 2 and faults == 0 and late == 0, out
    assert trips == 0
    en = [(c, v) for p, c, v in edges if p == BOARD.EN_PIN]
    assert [v for _, v in en] == [1, 0], en  # on once, off once -- after the loop ended
    writes = [c for c, *_ in ev if en[0][0] <= c <= en[1][0]]
    gaps = [(b - a) / US for a, b in zip(writes, writes[1:])]
    assert len(writes) >= 550 and max(gaps) < 1.5 * PERIOD_US, max(gaps)
    cut = (en[1][0] - writes[-1]) / US
    assert TIMEOUT_US <= cut < TIMEOUT_US + 50, cut


@pytest.mark.parametrize("kind", list(INJECT))
def test_a_hang_cuts_the_enable_within_three_periods(board: EmulatedBoard, kind: str) -> None:
    board.exec(SETUP + f"AT = {AT}\n" + INJECT[kind], timeout=5.0)
    board.usb_write(b"app.sup.arm()\napp.run(2000)\n\x04")
    edges, ev, resets, _ = H.collect_pins(board, 900, until=lambda e, rs: bool(rs))
    hang = [c for p, c, v in edges if p == MARK and v == 1]
    assert hang and resets, (kind, hang, resets)
    t_hang = hang[0]
    en = [(c, v) for p, c, v in edges if p == BOARD.EN_PIN]
    assert en and en[0][1] == 1 and en[0][0] < t_hang, en  # balancing, the driver on
    falls = [c for c, v in en if v == 0 and c > t_hang]
    assert falls, en
    t_cut = falls[0]
    assert not [c for c, v in en if en[0][0] < c < t_cut], "EN changed between balancing and the cut"
    before = [e for e in ev if e[0] < t_hang]
    assert before and before[-1][1] != 0  # the motor was driven up to the hang
    t_last = before[-1][0]  # the last motor command (and refresh): the last good tick
    assert not [e for e in ev if t_hang < e[0] < resets[0][0]], "PWM written after the hang"
    since_last = (t_cut - t_last) / US
    since_hang = (t_cut - t_hang) / US
    # the tick before the last motor command: it completed (step and poll) whatever the hang point
    since_prev = (t_cut - before[-2][0]) / US
    print(f"\n{kind}: EN low {since_last:.0f} us after the last motor command, {since_prev:.0f} us after the one "
          f"before, {since_hang:.0f} us after the hang; "
          f"reset {(resets[0][0] - t_hang) / US / 1000:.1f} ms after the hang")
    # the dead-man's timeout from the last refresh, not something else, cut it
    assert TIMEOUT_US <= since_last < TIMEOUT_US + 50, since_last
    assert max(since_last, since_prev, since_hang) <= 3 * PERIOD_US, (since_last, since_prev, since_hang)
    # the hardware watchdog still resets the board, its pins back to inputs (driver off)
    dt_ms = (resets[0][0] - t_hang) / US / 1000
    assert BOARD.WDT_MS - 5 <= dt_ms <= BOARD.WDT_MS + 5, dt_ms
    r = board.run(2000)
    assert r.en is None and r.duty == 0
    board._raw = False
    board._usb_buf.clear()
    board.enter_raw_repl(timeout=3)
    out = board.exec("import firmware.board as B\nfrom firmware.hal_pico import HalPico\nh = HalPico(B)\n"
                     "print(h.reset_cause())")
    assert out.split() == [str(T.RC_WATCHDOG)]


def test_the_emulation_of_the_pins_is_exact() -> None:
    # the harness steps the PIO lazily (caught up when the CPU looks, edges stamped at the PIO's
    # own cycle) and skips stalls and steady states; against the reference (every machine
    # stepped after every CPU instruction, no skips) on two fresh boards fed the same requests:
    # the same EN edges at the same cycles, the same PWM writes, the same encoder reads -- with
    # the dead-man refreshed, expiring (the last gap, 3.6 ms, is over its 3.49 ms) and
    # re-enabled, and encoder edges arriving while the CPU reads the decoder's FIFO
    code = (b"hal.set_enable(1)\nv = []\nfor i in range(8):\n    hal.set_motor(2000)\n    v.append(hal.read_encoder())\n"
            b"    time.sleep_us(1500 + 300 * i)\nhal.set_motor(0)\nprint(v, hal.deadman_trips())\n\x04")
    seen = []
    for exact in (False, True):
        with EmulatedBoard(main=False) as b:
            b._request({"cmd": "config", "watch": [BOARD.DIR_PIN, BOARD.EN_PIN], "pio_exact": exact})
            b.exec("import time\nimport firmware.board as B\nfrom firmware.hal_pico import HalPico\nhal = HalPico(B)\n"
                   f"hal.set_period({PERIOD_US})", timeout=3.0)
            b.set_encoder(300)
            b.usb_write(code)
            edges, ev, _, _ = H.collect_pins(b, 45)
            out = b._read_until(b"\x04", 1e6).decode()
            seen.append((edges, ev, out))
    (e0, p0, o0), (e1, p1, o1) = seen
    assert [v for p, _, v in e0 if p == BOARD.EN_PIN] == [1, 0, 1, 0], e0  # on, expired, on again, off
    assert o0.replace("\x04", " ").split()[-1] == "1"  # the expiry, counted by the refresh that came after it
    assert e0 == e1 and p0 == p1 and o0 == o1
