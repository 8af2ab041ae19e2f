"""Encoder counts between the virtual robot and the board (issue 22): the quadrature edges the
robot's pins drive (host/hil/virtual_robot.py, host/hil/emulated.py ``PinDrive``, the harness's
edge generation) arrive at the board's PIO counter exactly -- none lost or doubled, no step the
firmware's one-tick jump check (``encj``) would take for a fault.

The first test is offline (a recording stand-in for the board's pins); the second boots one
emulated Pico at its REPL and reads the real HalPico's PIO count back after edge patterns the old
edge generation lost counts on."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from sim import sensors
from sim.params import DEFAULT_PATH, load_params


class _Pins:
    # the board's pin inputs as the virtual robot drives them (EmulatedBoard's setters)
    def __init__(self) -> None:
        self.targets: list[int] = []

    def set_adc(self, value: int, channel: int = 0, *, open: bool = False) -> None:
        pass

    def set_supply_mv(self, mv: float) -> None:
        pass

    def set_encoder(self, count: int, within_us: float | None = None) -> None:
        self.targets.append(int(count))


def _ticks(robot: Any, n: int) -> None:
    # n plant ticks: the reading on the pins, one tick with the driver off (the hand holds the cart)
    for _ in range(n):
        robot.before()
        robot.plant.step(0, driven=0.0)


def test_after_a_reset_the_encoder_follows_the_cart_from_where_it_stands() -> None:
    # A reset (``hands reset``, test_readme_robot's test_4) powers the board up with its counter at 0.
    # The robot's pins followed from a fresh PinDrive, which took the plant's whole 16-bit reading
    # (the cart 0.2 m out: 1,100+ counts) for one tick's travel: a burst of edges the firmware,
    # already reading, saw as one step far beyond `encj` (enc_jump latched before any tool ran).
    from host.hil.virtual_robot import Hand, VirtualRobot

    robot = VirtualRobot(load_params(DEFAULT_PATH))
    pins = _Pins()
    robot.attach(pins)
    p = robot.plant
    p.hand = Hand(cart="still")
    p._x[0] = 0.2  # the cart pushed out (calibrate's "push the cart") and held there
    _ticks(robot, 2 * p.sensor_model.delay_steps + 4)
    cpm = float(sensors.enc_counts_per_m(robot.params))
    assert abs(pins.targets[-1] - 0.2 * cpm) <= 1  # the board counted the push
    pins.targets.clear()
    robot.power_cycled()  # the board restarted: its counter at 0 again
    _ticks(robot, 20)
    assert all(t == 0 for t in pins.targets), pins.targets[:5]  # the cart stood still: no edge
    # then rolled 10 mm: exactly that many counts from the reset's 0
    p._x[0] = 0.21
    _ticks(robot, 2 * p.sensor_model.delay_steps + 4)
    assert abs(pins.targets[-1] - 0.01 * cpm) <= 1, pins.targets[-3:]


HAL = "import firmware.board as B\nfrom firmware.hal_pico import HalPico\nhal = HalPico(B)\n"


@pytest.fixture(scope="module")
def board(tmp_path_factory: pytest.TempPathFactory):
    from host.boards.rp2040.board import EmulatedBoard, build_bundle

    bundle: Path = build_bundle(tmp_path_factory.mktemp("bundle"))
    with EmulatedBoard(bundle, main=False) as b:
        b.exec(HAL)
        yield b


def _count(b: Any) -> int:
    return int(b.exec("print(hal.read_encoder())", timeout=0.5))


@pytest.mark.slow
@pytest.mark.rp2040
def test_the_pio_counts_every_edge_of_large_jumps_and_reversals(board: Any) -> None:
    b = board
    assert _count(b) == 0  # the harness's position and the PIO's count both start at 0
    # a jump with more edges than fit in one run at a PIO-safe pace: the old harness squeezed the
    # 20,000 edges into the run's first 40 us (2 ns apart, several per PIO sampling pass: counts
    # lost); now they go on at 0.25 us each into the following runs
    b.set_encoder(20_000, within_us=40.0)
    b.run(500)
    b.run(6000)
    assert _count(b) == 20_000
    # a new target while edges are still pending, the other way: the old harness applied the pending
    # 2,000-odd edges at once (a Gray-code jump the decoder cannot follow), then reversed
    b.set_encoder(23_000)
    b.run(200)  # 800 of 3,000 edges at 0.25 us
    b.set_encoder(19_000)
    b.run(2000)
    assert _count(b) == 19_000
    # and across the 16-bit wrap, backwards: exact
    b.set_encoder(-3_000)
    b.run(6000)
    assert _count(b) == (-3_000) & 0xFFFF
