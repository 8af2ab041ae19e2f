"""The design toolkit for any cart-pole, as python-control objects (``upright design --json``).

One function per design step, each taking the robot (:class:`sim.params.RobotParams`, from
a robot file in either form) and returning python-control objects or plain arrays, so a
user can go on in python-control::

    from sim.params import load_params
    from host.design import toolkit as tk

    p = load_params("my_robot.toml")           # M, m, b, L_cm, I_cm or I_pivot, g
    G = tk.plant(p)                           # control.StateSpace, states x, xdot, phi, phidot
    K = tk.lqr(p, Q=[1, 0, 10, 0], R=0.01).K  # u = -K x + Nbar r
    L = tk.observer(p, [-20, -21, -22, -23]).L
    ctrl = tk.observer_controller(p, K, L)    # control.StateSpace, inputs x, phi, r; output F
    Gd = tk.discrete_plant(p, rate=500)        # control.StateSpace, dt = 1/500 (ZOH)

:func:`design` runs every requested step and returns the JSON-ready dictionary that
``upright design --json`` writes.  :data:`CONVENTIONS` states the conversions (state order,
signs, ``theta = pi + phi``, units) and goes into every output.
"""

from host.design.toolkit.core import (CONVENTIONS, Observer, StateFeedback, complex_list, kalman, lqr, margins,
                                      observer, observer_controller, pid, place, plant, plant_nonlinear,
                                      poles_from_spec, precompensator, reduced, reduced_controller_ss,
                                      state_feedback_loop, transfer_functions)
from host.design.toolkit.sampled import (discrete_observer_controller, discrete_plant, dkalman, dlqr, dobserver,
                                         dplace)
from host.design.toolkit.summary import design

__all__ = [
    "CONVENTIONS", "StateFeedback", "Observer", "plant", "plant_nonlinear", "transfer_functions", "poles_from_spec",
    "lqr", "place", "precompensator", "observer", "kalman", "reduced", "pid", "state_feedback_loop",
    "observer_controller", "reduced_controller_ss", "margins", "discrete_plant", "dlqr", "dplace", "dobserver",
    "dkalman", "discrete_observer_controller", "design", "complex_list",
]
