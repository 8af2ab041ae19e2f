"""The float reference: the same scenario closed with the float discrete design in pure simulation."""

from __future__ import annotations

from typing import Any

import numpy as np

from sim.params import RobotParams
from sim.plantsim import run_scenario_float
from sim.scenario import Scenario

__all__ = ["float_reference"]


def float_reference(scenario: Scenario, params: RobotParams, *, init: str = "measured",
                    seed: int | None = None, ctrl: Any = None, plant: RobotParams | None = None,
                    supply_measured: bool = False) -> dict[str, np.ndarray]:
    """The same scenario closed with the float discrete design in pure simulation.

    The controller is :func:`host.design.discrete.controller_for` of the *design* parameters
    ``params`` (the gains the firmware carries, with the estimator designed for the
    scenario's measurement noise as :meth:`host.hil.session.HilSession.prepare` uploads it);
    the plant gets the scenario's overrides.  The loop is the plant simulator's own,
    :func:`sim.plantsim.run_scenario_float`, started the way the firmware starts.

    Parameters
    ----------
    scenario : Scenario
        The scenario.
    params : RobotParams
        Design (and base plant) parameters.
    init : {"measured", "zero"}
        Initial controller state.  ``"measured"`` (default) starts it the way the firmware
        does when balancing starts: the estimate of the (delayed) state is the first
        measurement -- tilt from the ADC, cart position 0 (the firmware zeroes its
        encoder position then), speeds 0 -- and the stored forces are empty.  ``"zero"``
        starts from ``z = 0`` exactly as :func:`~sim.plantsim.run_scenario_float`'s default.
    seed : int, optional
        Noise seed overriding the scenario's.
    ctrl : DiscreteController, optional
        Another design (the one whose table :meth:`~host.hil.session.HilSession.use_gains`
        uploaded).
    plant : RobotParams, optional
        The simulated robot when it is not the design's (``--plant``).
    supply_measured : bool
        The firmware inverts the motor with the robot's measured supply (the emulated board
        with the default divider, :attr:`host.hil.emulated.EmulatedHil.measures_supply`).

    Returns
    -------
    dict of ndarray
        The run log, :func:`~sim.plantsim.run_scenario_float`'s (with ``x_meas``,
        ``phi_meas``, ``xdot_est``).
    """
    from host.design.discrete import controller_for

    if init not in ("measured", "zero"):
        raise ValueError(f"init must be 'measured' or 'zero', got {init!r}")
    ctrl = controller_for(scenario, params) if ctrl is None else ctrl
    return run_scenario_float(scenario, params, ctrl, init=init, seed=seed, plant=plant, supply_measured=supply_measured)
