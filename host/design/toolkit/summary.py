"""Every requested design step at once, JSON-ready: what ``upright design --json`` writes
(re-exported by :mod:`host.design.toolkit` as ``design``)."""

from __future__ import annotations

import math
from typing import Any, Sequence

import control as ct
import numpy as np

from host.design import analysis
from host.design import controllers as _ctl
from host.design.discrete import DiscreteController, closed_loop_poles, delayed_plant
from host.design.reduced import discrete_reduced_observer, reduced_controller
from host.design.toolkit.core import (CONVENTIONS, Observer, StateFeedback, _input_loop, _mat, _weights, complex_list,
                                      kalman, lqr, margins, observer, observer_controller, pid, place, plant,
                                      poles_from_spec, reduced, reduced_controller_ss, state_feedback_loop,
                                      transfer_functions)
from host.design.toolkit.sampled import (discrete_observer_controller, discrete_plant, dkalman, dlqr, dobserver,
                                         dplace)
from sim.params import RobotParams
from sim.plant import STATES, linear_model
from sim.robot_file import missing_sections

__all__ = ["design"]


def _ctrl_dict(c: DiscreteController, params: RobotParams, state: str) -> dict[str, Any]:
    return {"state": state, "Ac": _mat(c.Ac), "Bc": _mat(c.Bc), "Cc": _mat(c.Cc), "Dc": _mat(c.Dc), "Bu": _mat(c.Bu),
            "kr": c.kr, "closed_loop_poles": complex_list(closed_loop_poles(params, c))}


def _tf_dict(tf: ct.TransferFunction) -> dict[str, Any]:
    num = np.atleast_1d(np.squeeze(tf.num[0][0])).astype(float)
    den = np.atleast_1d(np.squeeze(tf.den[0][0])).astype(float)
    return {"num": num.tolist(), "den": den.tolist(), "zeros": complex_list(tf.zeros()), "poles": complex_list(tf.poles())}


def design(
    params: RobotParams,
    *,
    Q: Sequence[float] | None = None,
    R: float | None = None,
    poles: Sequence[complex] | None = None,
    spec: tuple[float, float] | None = None,
    observer_poles: Sequence[complex] | None = None,
    noise: Sequence[float] | None = None,
    reduced_poles: Sequence[complex] | None = None,
    pid_gains: Sequence[float] | None = None,
    rate: float | None = None,
    delay: float = 0.0,
) -> dict[str, Any]:
    """Every requested design step, JSON-ready (what ``upright design --json`` writes).

    Parameters
    ----------
    params : RobotParams
    Q, R : optional
        LQR weights (4 diagonal weights, ``R`` > 0); both or neither.
    poles : 4 complex, optional
        Pole placement.  ``spec = (overshoot, settling)`` gives them instead (:func:`poles_from_spec`).
    observer_poles : 4 complex, optional
        Full-order Luenberger observer.
    noise : (sigma_force, sigma_x, sigma_phi), optional
        Kalman filter instead of (or besides) the observer poles.
    reduced_poles : 2 complex, optional
        Reduced-order observer of ``[xdot, phidot]``.
    pid_gains : (Kp, Ki, Kd), optional
        PID on the angle (derivative filtered at ``DERIVATIVE_FILTER`` rad/s).
    rate : float, optional
        Loop rate (Hz): adds the ``discrete`` section.
    delay : float
        Measurement delay (s), a whole number of ticks at ``rate``.

    Returns
    -------
    dict
        ``conventions, robot, plant`` and, as requested, ``lqr, place, observer, kalman,
        reduced_observer, pid, controllers, discrete``.
    """
    if (Q is None) != (R is None):
        raise ValueError("LQR needs both Q and R")
    if poles is not None and spec is not None:
        raise ValueError("give the poles or the spec, not both")
    A, B, C, D = linear_model(params)
    G = plant(params)
    tfs = transfer_functions(params)
    _, det_wr, rank_wr = analysis.controllability(A, B)
    out: dict[str, Any] = {
        "conventions": CONVENTIONS,
        "robot": {"source": params.source, "M": params.M, "m": params.m, "b": params.b, "L_cm": params.L,
                  "I_cm": params.I_cm, "I_pivot": params.I_pivot, "g": params.g,
                  "missing_sections": sorted(missing_sections(params.values))},
        "plant": {"states": list(STATES), "inputs": ["F"], "outputs": ["x", "phi"], "A": _mat(A), "B": _mat(B),
                  "C": _mat(C), "D": _mat(D), "poles": complex_list(np.linalg.eigvals(A)),
                  "tf": {k: _tf_dict(v) for k, v in tfs.items()},
                  "controllability": {"det_Wr": det_wr, "rank": rank_wr},
                  "observability": {"rank": analysis.observability_rank(A, C)}},
    }
    feedback: dict[str, StateFeedback] = {}
    if Q is not None:
        feedback["lqr"] = lqr(params, Q, R)  # type: ignore[arg-type]
        out["lqr"] = {"Q": _mat(_weights(Q, R)[0]), "R": float(R), **feedback["lqr"].as_dict()}  # type: ignore[arg-type]
    if spec is not None:
        poles = poles_from_spec(*spec)
    if poles is not None:
        feedback["place"] = place(params, poles)
        out["place"] = {"spec": list(spec) if spec is not None else None, **feedback["place"].as_dict()}
    ests: dict[str, Observer] = {}
    if observer_poles is not None:
        ests["observer"] = observer(params, observer_poles)
        out["observer"] = ests["observer"].as_dict()
    if noise is not None:
        ests["kalman"] = kalman(params, noise[0], noise[1:])
        out["kalman"] = {"sigma_force": noise[0], "sigma_x": noise[1], "sigma_phi": noise[2], **ests["kalman"].as_dict()}
    red = None
    if reduced_poles is not None:
        red = reduced(params, reduced_poles)
        out["reduced_observer"] = {"Lr": _mat(red.Lr), "F": _mat(red.F), "G": _mat(red.G), "H": _mat(red.H),
                                   "poles": complex_list(red.poles)}
    loops: dict[str, Any] = {}
    for name, sf in feedback.items():
        loops[f"{name} (state feedback)"] = {"margins": margins(state_feedback_loop(params, sf.K))}
        for ename, ob in ests.items():
            cs = observer_controller(params, sf.K, ob.L, sf.Nbar)
            cl = ct.feedback(G, cs[:, :2], sign=1)
            loops[f"{name} + {ename}"] = {"A": _mat(cs.A), "B": _mat(cs.B), "C": _mat(cs.C), "D": _mat(cs.D),
                                         "closed_loop_poles": complex_list(cl.poles()),
                                         "margins": margins(_input_loop(params, cs))}
        if red is not None:
            cs = reduced_controller_ss(params, sf.K, red, sf.Nbar)
            cl = ct.feedback(G, cs[:, :2], sign=1)
            loops[f"{name} + reduced_observer"] = {"A": _mat(cs.A), "B": _mat(cs.B), "C": _mat(cs.C), "D": _mat(cs.D),
                                                  "closed_loop_poles": complex_list(cl.poles()),
                                                  "margins": margins(_input_loop(params, cs))}
    if pid_gains is not None:
        Cp = pid(*pid_gains)
        Lp = tfs["phi"] * Cp
        out["pid"] = {"Kp": pid_gains[0], "Ki": pid_gains[1], "Kd": pid_gains[2], "N": _ctl.DERIVATIVE_FILTER,
                      "tf": _tf_dict(Cp), "closed_loop_poles": complex_list(ct.feedback(Lp, 1).poles()),
                      "margins": margins(Lp)}
    if loops:
        out["controllers"] = loops
    if rate is not None:
        out["discrete"] = _discrete(params, rate, delay, feedback, Q, R, poles, observer_poles, noise, reduced_poles)
    return out


def _discrete(params: RobotParams, rate: float, delay: float, feedback: dict[str, StateFeedback],
              Q: Any, R: Any, poles: Any, observer_poles: Any, noise: Any, reduced_poles: Any) -> dict[str, Any]:
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"rate must be > 0 Hz, got {rate!r}")
    ticks = delay * rate
    if delay < 0 or abs(ticks - round(ticks)) > 1e-6:
        raise ValueError(f"delay must be a whole number of ticks of {1e3 / rate:g} ms, got {delay!r} s")
    d = int(round(ticks))
    Gd = discrete_plant(params, rate)
    out: dict[str, Any] = {"rate": rate, "Ts": 1.0 / rate, "delay": delay, "delay_steps": d,
                           "plant": {"A": _mat(Gd.A), "B": _mat(Gd.B), "C": _mat(Gd.C), "D": _mat(Gd.D),
                                     "poles": complex_list(np.linalg.eigvals(Gd.A))}}
    if d:
        Ax, Bx, Cx, _, _ = delayed_plant(params, rate, delay)
        out["delayed_plant"] = {"states": "[x, xdot, phi, phidot, y[k-1], ..., y[k-d]] (y = [x, phi])",
                                "A": _mat(Ax), "B": _mat(Bx), "C": _mat(Cx)}
    fb: dict[str, StateFeedback] = {}
    if "lqr" in feedback:
        fb["lqr"] = dlqr(params, Q, R, rate)
    if "place" in feedback:
        fb["place"] = dplace(params, poles, rate)
    for k, v in fb.items():
        out[k] = v.as_dict()
    ests: dict[str, Observer] = {}
    if observer_poles is not None:
        ests["observer"] = dobserver(params, observer_poles, rate)
    if noise is not None:
        ests["kalman"] = dkalman(params, noise[0], noise[1:], rate)
    ctrls: dict[str, Any] = {}
    for ename, ob in ests.items():
        out[ename] = ob.as_dict()
        for k, v in fb.items():
            c = discrete_observer_controller(params, v.K, ob.L, rate, delay)
            ctrls[f"{k} + {ename}"] = _ctrl_dict(c, params, "[p (4): the a-priori estimate of x[k-d], u[k-d], ..., "
                                                          "u[k-1]]; u = Cc z + Dc [x, phi, r], z' = Ac z + Bc [x, phi, r] "
                                                          "+ Bu u")
    if reduced_poles is not None:
        ro = discrete_reduced_observer(params, reduced_poles, rate)
        out["reduced_observer"] = {"Lr": _mat(ro.Lr), "F": _mat(ro.F), "G": _mat(ro.G), "H": _mat(ro.H),
                                   "poles": complex_list(ro.poles)}
        for k, v in fb.items():
            rc = reduced_controller(params, v.K, reduced_poles, rate, delay)
            ctrls[f"{k} + reduced_observer"] = _ctrl_dict(rc, params, "[z (2), u[k-d], ..., u[k-1]]; u = Cc z + Dc "
                                                                      "[x, phi, r], z' = Ac z + Bc [x, phi, r] + Bu u")
    if ctrls:
        out["controllers"] = ctrls
    return out
