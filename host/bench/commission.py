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

import math
import os
import tempfile
import time
from typing import Any

import numpy as np

__all__ = ["bench", "robots", "true_verdict", "commission_one"]


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


def commission_one(label: str, plant: Any) -> dict[str, Any]:
    """One robot of the bench: the shipped table verified, then commissioned and verified again (module docstring)."""
    from host.operate.commission import Commission, CommissionError, weighed
    from host.operate.commission_lockstep import LockstepRobot
    from host.studies.identify import robot_toml
    from sim.params import load_params
    from sim.scenario import load_scenario

    design = load_params()
    scen = [load_scenario("ref_step_20cm"), load_scenario("push_0p2N_5s")]
    row: dict[str, Any] = {"robot": label}
    t0 = time.monotonic()
    with LockstepRobot(plant) as r:
        r.fw_params = design  # the shipped table (the firmware's own; nothing uploaded)
        before = [true_verdict(r.run_scenario(sc), sc, plant) for sc in scen]
        row["shipped"] = all(v["pass"] for v in before)
        row["shipped_fell"] = any(v["fell"] for v in before)
        row["shipped_worst"] = _worst(before, plant)
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
                why = ""
            except CommissionError as exc:
                data, refused = c.state["data"], str(exc).split(":")[0]
                why = str(exc)
                lost = "fell" in str(exc)
            row["seconds"] = time.monotonic() - t1
            # a loss is the plant's truth: a balancing try whose pendulum passed phi_max, a
            # stage that refused after a fall, a verification run that fell (below, re-run)
            lost = lost or any(t.get("fell") for t in data.get("balance", {}).get("tries", []))
            ver = data.get("verify", {})
            row["refused"] = refused
            row["why"] = why[:200]
            row["verified"] = bool(ver) and all(v.get("pass", False) for v in ver.values())
            row["margin"] = data.get("design2", {}).get("margin", math.nan)
            row["deadband_est"] = data.get("cart", {}).get("estimates", {}).get("deadband", math.nan)
            row["id_err"] = _id_errors(data, plant)
            if ver:
                after = [true_verdict(r.run_scenario(sc), sc, plant) for sc in scen]
                row["after"] = all(v["pass"] for v in after)
                row["after_settle"] = max(v["settle"] for v in after)
                row["after_xdd"] = max(v["peak_xddot"] for v in after)
                row["after_phi"] = max(v["peak_phi"] for v in after)
                row["after_worst"] = _worst(after, plant)
                row["verified_but_false"] = row["verified"] and not row["after"]
                lost = lost or any(v["fell"] for v in after)
            else:
                row["after"] = False
        row["lost"] = lost
    row["wall_s"] = time.monotonic() - t0
    return row


def _worst(verdicts: list[dict[str, Any]], p: Any) -> float:
    # the largest value/limit of the report's constraints over the runs (> 1: failed)
    return float(max(max(v["peak_phi"] / p.phi_max, v["peak_xddot"] / p.a_max, v["settle"] / p.t_settle)
                     for v in verdicts))


def _id_errors(data: dict[str, Any], plant: Any) -> dict[str, float]:
    # relative errors of the identified I, m L, kt, b; the deadband's absolute error (fraction of full duty)
    e = data.get("identify", {}).get("estimates", {})
    truth = {"I": plant.I, "mL": plant.m * plant.L, "kt": plant.kt, "b": plant.b}
    out = {k: float(e[k] / v - 1.0) for k, v in truth.items() if k in e and v}
    ce = data.get("cart", {}).get("estimates", {})
    if "deadband" in ce:
        out["deadband"] = float(ce["deadband"] - plant.realism["deadband"])
    return out


def _one(args: tuple[str, Any]) -> dict[str, Any]:
    try:
        return commission_one(*args)
    except Exception as exc:  # noqa: BLE001 - a robot the harness could not run is a row, not a crash
        return {"robot": args[0], "error": f"{type(exc).__name__}: {exc}"[:300], "shipped": False, "after": False,
                "lost": False, "refused": "harness", "seconds": math.nan}


def _progress(row: dict[str, Any]) -> None:
    # each robot's row as it is done, one JSON line (UPRIGHT_BENCH_COMMISSION_ROWS: a file to append to)
    path = os.environ.get("UPRIGHT_BENCH_COMMISSION_ROWS")
    if path:
        import json

        with open(path, "a") as fh:
            fh.write(json.dumps(row, default=float) + "\n")


def bench(n: int | None = None, jobs: int | None = None) -> dict[str, Any]:
    """Commission ``n`` robots in ``jobs`` processes (module docstring; ``UPRIGHT_BENCH_COMMISSION_N``,
    ``UPRIGHT_BENCH_COMMISSION_JOBS``, default 2: each a firmware process of its own)."""
    n = int(os.environ.get("UPRIGHT_BENCH_COMMISSION_N", "50")) if n is None else int(n)
    jobs = int(os.environ.get("UPRIGHT_BENCH_COMMISSION_JOBS", "2")) if jobs is None else int(jobs)
    todo = robots(n)
    if jobs > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(jobs) as pool:
            rows = []
            for row in pool.imap(_one, todo, chunksize=1):
                rows.append(row)
                _progress(row)
    else:
        rows = []
        for t in todo:
            rows.append(_one(t))
            _progress(rows[-1])
    k = len(rows)
    secs = [r["seconds"] for r in rows if math.isfinite(r.get("seconds", math.nan))] or [math.nan]
    refused: dict[str, int] = {}
    for r in rows:
        if r.get("refused"):
            refused[r["refused"]] = refused.get(r["refused"], 0) + 1
    vbf = sum(bool(r.get("verified_but_false")) for r in rows)
    notes = [f"{k} robots of sim/uncertainty_realistic.toml (nominal, vertices at the roughest realism, random)",
             f"meet every report constraint (step + push, true traces): shipped table {sum(r['shipped'] for r in rows)}/{k}, "
             f"after commissioning {sum(r['after'] for r in rows)}/{k} (target >= 95 %)",
             f"lost the pendulum during commissioning: {sum(r['lost'] for r in rows)} (target 0); "
             f"stages refused: {sum(bool(r['refused']) for r in rows)} {refused}",
             f"verified from telemetry but failing in truth: {vbf}",
             f"time per commissioning: median {np.median(secs):.1f} s, max {max(secs):.1f} s (lockstep HIL, unix port, "
             f"{jobs} processes)"]
    return {"title": "commission: robots of the realistic set, end to end in lockstep HIL", "rows": rows, "notes": notes,
            "summary": {"robots": k, "shipped_pass": sum(r["shipped"] for r in rows),
                        "after_pass": sum(r["after"] for r in rows), "lost": sum(r["lost"] for r in rows),
                        "verified_but_false": vbf, "refused": refused, "median_s": float(np.median(secs))}}
