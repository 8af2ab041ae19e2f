"""Hardware cut-offs on the emulated board (issue 13 item 2), measured on the pins.

* e-stop (board.ESTOP_PIN, active low): the pin IRQ drives EN low and writes PWM compare 0 within
  tens of microseconds; the loop latches F_ESTOP on its next tick;
* a hung loop (a step that never returns; a blocking UART write): the driver-enable dead-man
  (a PIO state machine the loop refreshes in set_motor) drops EN board.DEADMAN_PCT % of a period
  after the last motor command; then the hardware watchdog (board.WDT_MS = 100 ms) resets the
  chip -- PWM and EN fall back to inputs -- and the next boot reads the reset-cause marker
  (RC_WATCHDOG) the loop left in WATCHDOG SCRATCH3 (tests/test_rp2040_deadman.py measures the
  dead-man at four hang points of the shipped viper loop; here the bytecode loop);
* direction changes: DIR flips only while the PWM output is low (duty 0 in force first).

Measured here (125 MHz emulated cycles, bytecode firmware): e-stop edge -> EN low 56 us (the
dead-man's "off" word; 28 us when EN was a CPU pin), -> PWM compare 0 written 22 us (in force at the next PWM wrap, <= 50 us); hang -> EN low 3.5 ms
after the last motor command (dead-man), -> reset (PWM and EN inputs) 98-99.3 ms, both hang kinds.
The bounds below are generous: the cut-off exists and is of that order, not the exact figure.
"""

from __future__ import annotations

import pytest

from firmware import board as BOARD
from firmware import msgtable as T
from firmware.supervisor import F_ESTOP
import fwharness as H
from host.boards.rp2040.board import EmulatedBoard

pytestmark = pytest.mark.rp2040  # slow; skipped without the emulated board (tests/conftest.py)

US = 125  # cycles per microsecond
MARK = 25  # a spare pin (the LED) the test code raises at the moment it hangs
SETUP = (
    "import firmware.board as B, machine\nfrom firmware.hal_pico import HalPico\nfrom firmware.app import App\n"
    "hal = HalPico(B)\nled = machine.Pin(25, machine.Pin.OUT, value=0)\n"
    "app = App(hal, config={'watchdog_ms': 0, 'stall_ms': 0, 'wdt_ms': B.WDT_MS})\n"
    "orig = hal.read_encoder\nN = [0]\n"
    "def enc():\n    N[0] += 1\n    if N[0] == 150:\n        led.value(1)\n        while True:\n            pass\n"
    "    return orig()\n"
    "U = machine.UART(1, 9600, tx=machine.Pin(4), rx=machine.Pin(5))\nBIG = bytes(20000)\n"
    "class Stuck:\n    def poll(s):\n        N[0] += 1\n        if N[0] >= 150:\n            led.value(1)\n"
    "            U.write(BIG)\n"
)


def _board() -> EmulatedBoard:
    b = EmulatedBoard(main=False)
    b._request({"cmd": "config", "watch": [BOARD.DIR_PIN, BOARD.EN_PIN, MARK], "pwm_edges": True})
    b.set_adc(2048 + 30)  # a little off upright: the controller drives the motor
    b.exec(SETUP)
    return b


def test_estop_cuts_pwm_and_enable_within_microseconds() -> None:
    with _board() as b:
        assert b.run(100).en == 0  # the driver is off until the supervisor balances
        b.usb_write(b"app.sup.arm()\napp.run(400)\nprint('done', app.sup.state, app.sup.faults)\n\x04")
        edges, ev, _, _ = H.collect_pins(b, 150)
        assert any(p == BOARD.EN_PIN and v == 1 for p, _, v in edges), "never balanced"
        assert any(e[1] != 0 for e in ev), "the motor never ran"
        t0 = b.cycles
        b.set_pin(BOARD.ESTOP_PIN, 0)
        edges, ev, _, r = H.collect_pins(b, 20)
        en_low = [c for p, c, v in edges if p == BOARD.EN_PIN and v == 0]
        pwm0 = [c for c, cmp_, *_ in ev if cmp_ == 0]
        if en_low and pwm0:
            print(f"\ne-stop: EN low {(en_low[0] - t0) / US:.0f} us, PWM compare 0 {(pwm0[0] - t0) / US:.0f} us after")
        assert en_low and (en_low[0] - t0) / US < 200, en_low
        assert pwm0 and (pwm0[0] - t0) / US < 200, pwm0
        assert not [e for e in ev if e[1] != 0], "duty written after the e-stop"
        assert r.en == 0 and r.duty == 0
        b.set_pin(BOARD.ESTOP_PIN, None)
        out = b._read_until(b"\x04", 3e6).decode()
        state, faults = (int(v) for v in out.split("done")[1].split()[:2])
        assert state == 3 and faults & F_ESTOP


@pytest.mark.parametrize("kind", ["step", "write"])
def test_hung_loop_is_reset_by_the_hardware_watchdog(kind: str) -> None:
    with _board() as b:
        link = "app._read_enc = enc\n" if kind == "step" else "app.set_link(Stuck())\n"
        b.exec(link)
        b.usb_write(b"app.sup.arm()\napp.run(1000)\n\x04")
        edges, ev, resets, r = H.collect_pins(b, 600, until=lambda e, rs: bool(rs))
        hang = [c for p, c, v in edges if p == MARK and v == 1]
        assert hang and resets, (hang, resets)
        assert any(p == BOARD.EN_PIN and v == 1 for p, _, v in edges if p == BOARD.EN_PIN and _ < hang[0])
        assert not [e for e in ev if e[1] != 0 and e[0] > hang[0]]
        # the dead-man drops EN within three periods (2 ms) of the last motor command
        last = max(e[0] for e in ev if e[0] < hang[0])
        cut = [c for p, c, v in edges if p == BOARD.EN_PIN and v == 0 and c > hang[0]]
        assert cut and (cut[0] - last) / US <= 3 * 2000, (cut, last)
        dt_ms = (resets[0][0] - hang[0]) / US / 1000
        # the board's watchdog timeout, less the part of a tick between the last feed and the hang
        assert BOARD.WDT_MS - 5 <= dt_ms <= BOARD.WDT_MS + 5, dt_ms
        r = b.run(2000)
        assert r.en is None and r.duty == 0  # pins back to inputs (pad pull-downs): driver off
        # it boots again; the firmware's own marker says why
        b._raw = False
        b._usb_buf.clear()
        b.enter_raw_repl(timeout=3)
        out = b.exec("import firmware.board as B\nfrom firmware.hal_pico import HalPico\nh = HalPico(B)\n"
                     "print(h.reset_cause(), h.reset_cause())")
        assert out.split() == [str(T.RC_WATCHDOG), str(T.RC_POWER_ON)]  # read once, then cleared


def test_direction_changes_only_with_the_pwm_output_low() -> None:
    with _board() as b:
        b.exec("hal.set_enable(1)")
        b._request({"cmd": "config", "watch": [BOARD.DIR_PIN, BOARD.EN_PIN, BOARD.PWM_PIN], "pwm_edges": True})
        b.usb_write(b"import time\nfor k in range(40):\n    hal.set_motor(20000 if k % 2 else -20000)\n"
                    b"    time.sleep_us(170 + 13 * k)\nhal.set_motor(0)\n\x04")
        edges, _, _, _ = H.collect_pins(b, 30)
        level = 0
        flips = 0
        for p, c, v in sorted(edges, key=lambda e: e[1]):
            if p == BOARD.PWM_PIN:
                level = v
            elif p == BOARD.DIR_PIN:
                flips += 1
                assert level == 0, f"DIR flipped at cycle {c} with the PWM output high"
        assert flips >= 30
