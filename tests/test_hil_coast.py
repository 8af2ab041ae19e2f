"""The H-bridge with its enable (EN) low: every simulator lets the motor coast (issue 22).

The Pico drives the driver's enable (nSLEEP/INH, GP18) high only while balancing
(``App._drive``); with it low the bridge's outputs are off -- no current, so no force and no
back-EMF braking: the cart coasts.  Enabled at duty 0 the bridge shorts the motor (slow decay)
and brakes it.  The emulated-board HIL (``EmulatedHil``: :class:`sim.plantsim.PlantSim`), the
virtual robot (:class:`host.hil.virtual_robot.RobotPlant`) and the lockstep HIL all take the
part of the tick EN was high from the same place (:func:`host.hil.emulated.duty_over`, or the
board's state) and apply it the same way.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from host.boards.rp2040.board import StepResult
from host.hil.emulated import duty_over
from host.hil.virtual_robot import RobotPlant
from sim.params import load_params
from sim.plantsim import PlantSim
from sim.scenario import scenario_from_dict

TICKS = 250  # 0.5 s at 500 Hz


def _rolling(params) -> PlantSim:
    # the cart rolling at 0.5 m/s, the pendulum upright (it tips over slowly within 0.5 s)
    sc = scenario_from_dict({"name": "coast", "duration": 10.0, "initial": {"xdot": 0.5}})
    return PlantSim(params, sc)


def _robot(params) -> RobotPlant:
    r = RobotPlant(params)
    r.hand = None  # let go: the plant's own equations, as PlantSim's
    r._x = [0.0, 0.5, 0.0, 0.0]
    return r


@pytest.mark.parametrize("driven", [0.0, 0.5, 1.0])
def test_the_emulated_hil_plant_and_the_virtual_robot_agree_on_the_bridge(driven: float) -> None:
    p = load_params()
    a, b = _rolling(p), _robot(p)
    for _ in range(TICKS):
        a.step(0, driven=driven)
        b.step(0, driven=driven)
    assert np.allclose(a.state, b._x, rtol=0, atol=1e-12), (a.state, b._x)


def test_en_low_coasts_and_en_high_at_duty_0_brakes() -> None:
    p = load_params()
    coast, brake, half = _rolling(p), _rolling(p), _rolling(p)
    # the bridge off is the same as a motor without back-EMF (kt ~ 0: at duty 0 no force either)
    free = _rolling(p.replace(kt=1e-9))
    for _ in range(TICKS):
        coast.step(0, driven=0.0)
        brake.step(0)
        half.step(0, driven=0.5)
        free.step(0)
    assert np.allclose(coast.state, free.state, rtol=0, atol=1e-9), (coast.state, free.state)
    v_coast, v_half, v_brake = coast.state[1], half.state[1], brake.state[1]
    # the robot's back-EMF (44 N s/m) stops the cart within a few ms when braked; friction alone
    # (b = 0.1 N s/m on 0.5 kg, plus the pendulum's pull) keeps most of it rolling
    # (half the tick enabled still brakes: half the back-EMF damping, the cart stopped too)
    assert v_coast > 0.35 and abs(v_brake) < 0.05 and abs(v_half) < 0.05, (v_coast, v_half, v_brake)


def test_a_realistic_plant_coasts_too() -> None:
    # Coulomb friction, gear play and a deadband: the bridge off has no no-load speed to divide by
    p = load_params("sim/plants/realistic_cart.toml")
    sim = _rolling(p)
    for _ in range(TICKS):
        sim.step(0, driven=0.0)
    assert all(math.isfinite(v) for v in sim.state)
    assert 0.0 <= sim.state[1] < 0.5


def _result(c1: int, edges: list[tuple[int, int, int | None]]) -> StepResult:
    return StepResult(cycles=c1, pwm_compare=3125, pwm_top=6249, pwm_enabled=True, pwm_div=16, duty=0.5, dir=0,
                      en=edges[-1][2] if edges else 1, uart_tx=b"", uart_tx_cycles=[], usb_tx=b"", edges=edges,
                      pwm_events=[], uart_baud=1_000_000, halted=False, waiting=False, idle_cycles=0, pc=0, wall_s=0.0)


def test_duty_over_gives_the_part_of_the_tick_en_was_high() -> None:
    from firmware import board as fb

    state = {"compare": 3125, "top": 6249, "enabled": True, "dir": 0, "en": 1, "dir_pin": fb.DIR_PIN,
             "en_pin": fb.EN_PIN}
    # EN falls at the middle of the tick (a disarm): half the duty, half the tick driven
    d = duty_over(state, _result(250_000, [(fb.EN_PIN, 125_000, 0)]), 0, 250_000)
    assert state["en_frac"] == pytest.approx(0.5) and d == pytest.approx(0.25 * 32767, rel=1e-3)
    d = duty_over(state, _result(500_000, []), 250_000, 500_000)  # the next tick: EN low all through
    assert state["en_frac"] == 0.0 and d == 0.0
