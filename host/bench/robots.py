"""The robots the commissioning benches share, and how a run is judged against the report.

:func:`robots` draws the first ``n`` robots of ``sim/uncertainty_realistic.toml`` (the nominal
robot, every ``stride``-th vertex of the box -- each at the roughest plant realism -- and seeded
random points); :func:`true_verdict` judges a lockstep run's true traces against the report's
constraints, :func:`true_verdicts` runs scenarios and judges each, and :func:`failing_check` names
the first constraint a verdict fails; :func:`upload_true_table` gives a robot a table designed for
its true parameters.  Sections :mod:`host.bench.commission` and :mod:`host.bench.realism` both
use them.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["robots", "true_verdict", "true_verdicts", "failing_check", "upload_true_table"]


def robots(n: int) -> list[tuple[str, Any]]:
    """The first ``n`` robots of the realistic set: ``(label, RobotParams)`` (module docstring)."""
    from host.design.uncertainty import UNCERTAINTY_REALISTIC, load_uncertainty
    from sim.params import load_params

    base = load_params()
    us = load_uncertainty(UNCERTAINTY_REALISTIC)
    pts = us.points(float(base.rate), base.delay)
    nominal, vert, rand = pts[:1], [p for p in pts[1:] if p.vertex], [p for p in pts[1:] if not p.vertex]
    k_rand = min(len(rand), max(0, n // 3))
    k_vert = max(0, n - 1 - k_rand)
    stride = max(1, len(vert) // max(1, k_vert))
    chosen = (nominal + vert[::stride][:k_vert] + rand[:k_rand])[:max(0, n)]
    out = []
    for p in chosen:
        ch = dict(p.overrides(base))
        ch["sensors.delay"] = p.delay_ticks / float(base.rate)
        out.append((p.label(float(base.rate)), base.replace(**ch)))
    return out


def true_verdict(log: dict[str, np.ndarray], scenario: Any, params: Any) -> dict[str, Any]:
    """The run's true metrics (the plant's state) against the report's constraints."""
    from sim.metrics import compute_metrics

    lg = {"t": log["t"], "x": log["true_x"], "phi": log["true_phi"], "x_ref": log["x_ref"], "xddot": log["true_xddot"],
          "force": log["force"], "duty": log["duty"]}
    m = compute_metrics(lg, scenario, params)
    settle = math.inf if math.isnan(m.settling_time) else float(m.settling_time)
    fell = bool(m.peak_phi >= params.phi_max or np.any(np.asarray(log["state"]) != 2))
    ok = (not fell) and m.peak_xddot <= params.a_max and settle <= params.t_settle
    return {"peak_phi": float(m.peak_phi), "peak_xddot": float(m.peak_xddot), "settle": settle, "fell": fell, "pass": ok}


def true_verdicts(robot: Any, plant: Any, scen: Any) -> list[dict[str, Any]]:
    """:func:`true_verdict` of each scenario of ``scen`` run on ``robot`` (whose plant is ``plant``)."""
    return [true_verdict(robot.run_scenario(sc), sc, plant) for sc in scen]


def upload_true_table(robot: Any, plant: Any, cand: Any, **values: Any) -> None:
    """Upload to ``robot`` the table of candidate ``cand`` designed for ``plant``'s true parameters
    at the firmware's predictor length (the shipped design's delay), with its deadband and most of
    its Coulomb friction compensated as ``upright commission`` uploads them
    (:func:`host.operate.commission.compensation_counts`); ``values``: robot-file keys set on the
    design's file as well (``loop.ref_rate``: the set-point ramp the upload sets)."""
    from host.design.margin import fixed_design
    from host.operate.commission import compensation_counts
    from sim.params import load_params

    design = plant.replace(**{"sensors.delay": load_params().delay, **values})
    robot.upload(fixed_design(design, cand, deadband=compensation_counts(design)).blob(), design)


def failing_check(v: dict[str, Any], limits: Any) -> str:
    """The first report constraint a run's verdict ``v`` fails: ``fell``, ``phi``, ``xdd``, ``settle`` or ``""``."""
    if v["fell"]:
        return "fell"
    if v["peak_phi"] >= limits.phi_max:
        return "phi"
    if v["peak_xddot"] > limits.a_max:
        return "xdd"
    if not v["settle"] <= limits.t_settle:
        return "settle"
    return ""
