"""The robots the commissioning benches share, and how a run is judged against the report.

:func:`robots` draws the first ``n`` robots of ``sim/uncertainty_realistic.toml`` (the nominal
robot, every ``stride``-th vertex of the box -- each at the roughest plant realism -- and seeded
random points); :func:`true_verdict` judges a lockstep run's true traces against the report's
constraints and :func:`failing_check` names the first one a verdict fails.  Sections
:mod:`host.bench.commission` and :mod:`host.bench.realism` both use them.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["robots", "true_verdict", "failing_check"]


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
