"""``make bench`` section ``realism`` (issue 24): what fails where, by plant-realism parameter.

The commissioning bench (:mod:`host.bench.commission`) says how many robots of the realistic set
meet the report's constraints after commissioning; this section says *why* the others do not.
It takes the best a commissioning can do -- a gain table designed for each robot's **true**
parameters (a perfect identification), the drive's true deadband and most of its Coulomb friction
compensated by the firmware as ``upright commission`` uploads it
(:func:`host.operate.commission.compensation_counts`) --
and adds one plant-realism effect at a time, at fractions of its range's high end in
``sim/uncertainty_realistic.toml`` (``[realism]``), then all of them together:

* robots: the commissioning bench's first ``n`` robots (:func:`host.bench.robots.robots`:
  the nominal, vertices of the box, random points) with their realism removed, so each row
  changes one thing;
* the table: of the margin design's weight sets ``shipped`` at force clamps 4.73 and 4.2 m/s^2,
  the one that passes the ideal robot with the smaller worst ratio (value / limit), designed for
  the robot's true parameters at the firmware's predictor length;
* each run: the report's 20 cm step and 0.2 N push in lockstep HIL (the firmware on the unix port,
  :class:`host.operate.commission_lockstep.LockstepRobot`), judged on the true traces
  (:func:`host.bench.robots.true_verdict`).

Rows: robot, effect, level (fraction of the range's high end), the robot-file value, verdict,
the first constraint that fails (``settle``, ``xdd``, ``phi`` or ``fell``), worst settling time and
peak ``|xdd|``.  Notes: per effect and level how many robots pass, and the largest level at which
every robot still passes.  ``n`` robots (default 6; ``UPRIGHT_BENCH_REALISM_N``).
"""

from __future__ import annotations

import math
import os
from typing import Any, Sequence

__all__ = ["bench", "EFFECTS", "LEVELS", "study"]

EFFECTS: dict[str, tuple[str, ...]] = {
    "coulomb": ("coulomb",),
    "stiction": ("stiction",),
    "backlash": ("backlash",),
    "deadband": ("deadband",),
    "duty_min": ("duty_min",),
    "pot_inl": ("pot_inl",),
    "all": ("coulomb", "stiction", "backlash", "deadband", "duty_min", "pot_inl"),
}
"""Effect name -> the ``[realism]`` keys it sets (the others stay 0)."""

LEVELS: tuple[float, ...] = (0.1, 0.25, 0.5, 1.0)
"""Fractions of each range's high end."""


def _ratio(vs: Sequence[dict[str, Any]], p: Any) -> float:
    return max(max(v["peak_phi"] / p.phi_max, v["peak_xddot"] / p.a_max, v["settle"] / p.t_settle) for v in vs)


def study(n: int, effects: Sequence[str] = tuple(EFFECTS), levels: Sequence[float] = LEVELS) -> list[dict[str, Any]]:
    """The rows of the section (module docstring) for the first ``n`` robots, ``effects`` x ``levels``."""
    from host.bench.robots import failing_check, robots, true_verdicts, upload_true_table
    from host.design.margin import candidates
    from host.design.uncertainty import REALISM, UNCERTAINTY_REALISTIC, in_model, load_uncertainty
    from host.operate.commission_lockstep import LockstepRobot
    from sim.scenario import load_scenario

    ranges = load_uncertainty(UNCERTAINTY_REALISTIC).realism
    scen = [load_scenario("ref_step_20cm"), load_scenario("push_0p2N_5s")]
    cands = candidates(ki=(0.0,), a_cmd=(4.73, 4.2), names=("shipped",))
    rows: list[dict[str, Any]] = []
    for label, plant in robots(n):
        ideal = in_model(plant)
        best, best_r, ideal_v = cands[0], math.inf, None
        with LockstepRobot(ideal) as r:
            for c in cands:
                upload_true_table(r, ideal, c)
                vs = true_verdicts(r, ideal, scen)
                ok = all(v["pass"] for v in vs)
                rr = _ratio(vs, ideal) - (10.0 if ok else 0.0)
                if rr < best_r:
                    best, best_r, ideal_v = c, rr, vs
        assert ideal_v is not None
        rows.append({"robot": label, "effect": "ideal", "level": 0.0, "value": "", "table": best.name,
                     "pass": all(v["pass"] for v in ideal_v),
                     "fails": next((f for f in (failing_check(v, ideal) for v in ideal_v) if f), ""),
                     "settle": max(v["settle"] for v in ideal_v), "xdd": max(v["peak_xddot"] for v in ideal_v)})
        for eff in effects:
            for lev in levels:
                ch = {REALISM[k]: lev * float(ranges[k][1]) for k in EFFECTS[eff]}
                pl = ideal.replace(**ch)
                with LockstepRobot(pl) as r:
                    upload_true_table(r, pl, best)
                    vs = true_verdicts(r, pl, scen)
                rows.append({"robot": label, "effect": eff, "level": float(lev),
                             "value": " ".join(f"{k.split('.')[-1]}={v:.3g}" for k, v in ch.items()) if eff != "all"
                             else "all", "table": best.name, "pass": all(v["pass"] for v in vs),
                             "fails": next((f for f in (failing_check(v, pl) for v in vs) if f), ""),
                             "settle": max(v["settle"] for v in vs), "xdd": max(v["peak_xddot"] for v in vs)})
    return rows


def summary(rows: Sequence[dict[str, Any]]) -> list[str]:
    """One note per effect: passes per level, what fails, the largest level every robot passes."""
    import collections

    from host.operate.commission import COULOMB_COMP

    k = len({r["robot"] for r in rows})
    ideal = [r for r in rows if r["effect"] == "ideal"]
    notes = [f"{k} robots, each with a table designed for its true parameters (a perfect identification), its "
             f"true deadband and {COULOMB_COMP:g} x its Coulomb friction compensated; ideal plant: {sum(r['pass'] for r in ideal)}/{k} pass"]
    for eff in dict.fromkeys(r["effect"] for r in rows if r["effect"] != "ideal"):
        sel = [r for r in rows if r["effect"] == eff]
        levs = sorted({r["level"] for r in sel})
        per = {lv: [r for r in sel if r["level"] == lv] for lv in levs}
        ok = [lv for lv in levs if all(r["pass"] for r in per[lv])]
        safe = max((lv for lv in levs if all(lv2 in ok for lv2 in levs if lv2 <= lv)), default=None)
        why = collections.Counter(r["fails"] for r in sel if r["fails"])
        notes.append(f"{eff}: pass " + ", ".join(f"{100 * lv:g} % {sum(r['pass'] for r in per[lv])}/{len(per[lv])}"
                                                  for lv in levs)
                     + f" of the range's high end; every robot passes up to "
                     + (f"{100 * safe:g} %" if safe is not None else "none of the levels")
                     + ("; fails on " + ", ".join(f"{c} {m}" for c, m in why.most_common()) if why else ""))
    return notes


def bench(n: int | None = None) -> dict[str, Any]:
    """The section (module docstring)."""
    n = int(os.environ.get("UPRIGHT_BENCH_REALISM_N", "6")) if n is None else int(n)
    rows = study(n)
    return {"title": "realism: what fails where, one plant-realism effect at a time (tables for the true robot)",
            "rows": rows, "notes": summary(rows)}
