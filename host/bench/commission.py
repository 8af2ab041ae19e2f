"""``make bench`` section ``commission`` (issue 24 item 5): robots of the realistic set commissioned end to end.

Robots: the points of ``sim/uncertainty_realistic.toml`` (:meth:`UncertaintySet.points`: the
nominal robot, the box's vertices -- each at the roughest plant realism -- and seeded random
points), the first ``n`` of the nominal point, every ``stride``-th vertex and the random points
(corners included).  Each robot is a :class:`host.operate.commission_lockstep.LockstepRobot`
(the firmware under the unix port in lockstep HIL with the plant of that robot) and is

1. verified with the **shipped** gain table (the report's 20 cm step and 0.2 N push, the true
   traces against the report's constraints), then
2. commissioned end to end (:class:`host.operate.commission.Commission`, ``fast``; the robot file
   it starts from is ``sim/robot.toml`` with that robot's masses, as weighed), and verified
   again with the commissioned table (the commissioning's own telemetry verdict and the truth).

Rows: per robot the verdicts before/after, whether the pendulum was lost during commissioning
(a stage refused after a fall, or a verification run that fell), the stage that refused, the
worst design margin and the seconds it took; the summary: counts before and after, losses,
time per commissioning.  ``n`` robots (default 50; ``UPRIGHT_BENCH_COMMISSION_N``).
"""

from __future__ import annotations

import collections
import math
import os
import tempfile
import time
from typing import Any

import numpy as np

__all__ = ["bench", "robots", "true_verdict"]


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
    chosen = (nominal + vert[::stride][:k_vert] + rand[:k_rand])[:n]
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


def bench(n: int | None = None) -> dict[str, Any]:
    """Commission ``n`` robots (module docstring)."""
    from host.operate.commission import Commission, CommissionError, weighed
    from host.studies.identify import robot_toml
    from host.operate.commission_lockstep import LockstepRobot
    from sim.params import load_params
    from sim.scenario import load_scenario

    n = int(os.environ.get("UPRIGHT_BENCH_COMMISSION_N", "50")) if n is None else int(n)
    design = load_params()
    scen = [load_scenario("ref_step_20cm"), load_scenario("push_0p2N_5s")]
    rows: list[dict[str, Any]] = []
    for label, plant in robots(n):
        row: dict[str, Any] = {"robot": label}
        t0 = time.monotonic()
        with LockstepRobot(plant) as r:
            r.fw_params = design  # the shipped table (the firmware's own; nothing uploaded)
            before = [true_verdict(r.run_scenario(sc), sc, plant) for sc in scen]
            row["shipped"] = all(v["pass"] for v in before)
            row["shipped_fell"] = any(v["fell"] for v in before)
            lost = False
            with tempfile.TemporaryDirectory() as td:
                start = os.path.join(td, "weighed.toml")  # the robot file with the masses weighed
                with open(start, "w") as fh:
                    fh.write(robot_toml(weighed(design, plant)))
                c = Commission(r, td, params_in=start, say=lambda s: None, fast=True)
                t1 = time.monotonic()
                try:
                    data = c.run()
                    refused = ""
                except CommissionError as exc:
                    data, refused = c.state["data"], str(exc).split(":")[0]
                    row["why"] = str(exc)[:300]  # the stage's one line: what fails where
                    lost = "fell" in str(exc)
                row["seconds"] = time.monotonic() - t1
                ver = data.get("verify", {})
                row["refused"] = refused
                row["verified"] = bool(ver) and all(v.get("pass", False) for v in ver.values())
                row["margin"] = data.get("design2", {}).get("margin", math.nan)
                if ver:
                    after = [true_verdict(r.run_scenario(sc), sc, plant) for sc in scen]
                    row["after"] = all(v["pass"] for v in after)
                    row["after_settle"] = max(v["settle"] for v in after)
                    row["after_xdd"] = max(v["peak_xddot"] for v in after)
                    lost = lost or any(v["fell"] for v in after)
                else:
                    row["after"] = False
            row["lost"] = lost
        row["wall_s"] = time.monotonic() - t0
        rows.append(row)
    k = len(rows)
    secs = [r["seconds"] for r in rows]
    notes = [f"{k} robots of sim/uncertainty_realistic.toml (nominal, vertices at the roughest realism, random)",
             f"meet every report constraint (step + push, true traces): shipped table {sum(r['shipped'] for r in rows)}/{k}, "
             f"after commissioning {sum(r['after'] for r in rows)}/{k} (target >= 95 %)",
             f"lost the pendulum during commissioning: {sum(r['lost'] for r in rows)} (target 0); "
             f"stages refused: {sum(bool(r['refused']) for r in rows)}",
             "refused at: " + (", ".join(f"{st} {n}" for st, n in sorted(collections.Counter(
                 r["refused"] for r in rows if r["refused"]).items())) or "none"),
             f"time per commissioning: median {np.median(secs):.1f} s, max {max(secs):.1f} s (lockstep HIL, unix port)"]
    return {"title": "commission: robots of the realistic set, end to end in lockstep HIL", "rows": rows, "notes": notes,
            "summary": {"robots": k, "shipped_pass": sum(r["shipped"] for r in rows),
                        "after_pass": sum(r["after"] for r in rows), "lost": sum(r["lost"] for r in rows),
                        "median_s": float(np.median(secs))}}
