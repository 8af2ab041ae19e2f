"""``upright design --robust``: the design with the best worst case over the uncertainty set.

Prints the candidates ranked, then the worst case per scenario and constraint of the best
design and of the shipped one (value, limit, PASS/FAIL, how many points fail, where the worst
is), and whether the best meets every constraint over the whole set (the condition for shipping
it as the firmware default; the export command is printed).  ``--json FILE`` writes all of it.
Exit 0 in both cases: the search ran; whether a design passes is its result.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from typing import Any

from host.cli import args as A

__all__ = ["run_robust", "format_rows"]


def _f(v: Any) -> str:
    if isinstance(v, float):
        if math.isinf(v):
            return "never"
        if math.isnan(v):
            return "-"
        return f"{v:.4g}"
    return str(v)


def format_rows(rows: list[dict[str, Any]]) -> str:
    """The worst-case table as text (``never``: did not settle within the run)."""
    cols = ("scenario", "constraint", "worst", "limit", "verdict", "fails", "points", "at")
    cells = [[_f(r[c]) for c in cols] for r in rows]
    w = [max(len(c), *(len(x[i]) for x in cells)) for i, c in enumerate(cols)]
    lines = ["  ".join(c.ljust(n) for c, n in zip(cols, w)), "  ".join("-" * n for n in w)]
    lines += ["  ".join(x.ljust(n) for x, n in zip(row, w)) for row in cells]
    return "\n".join(lines)


def _jsonable(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return "never" if math.isinf(v) else None
    return v


def run_robust(args: argparse.Namespace) -> int:
    """Run the robust design search and print/write its result."""
    from host.design.robust import FORCE_LSB_MAX, UncertaintyError, load_uncertainty, worst_rows
    from host.design.robust_search import search
    from sim.params import load_params

    json_path = A.check_out_file(args.json, "--json")
    params = load_params(args.params)
    try:
        uset = load_uncertainty(args.uncertainty)
        pts = uset.points(float(params.rate), params.delay)
    except UncertaintyError as exc:
        raise A.UsageError(f"bad uncertainty file: {exc}") from None
    n_v = sum(p.vertex for p in pts)
    print(f"Robust design for {params.source} over {uset.source}: {len(pts)} robots "
          f"(nominal, {n_v} vertices, {uset.random} random points), {args.candidates} candidates, seed {args.seed}")
    print("supply: " + ("measured by the firmware (the default board's divider): a supply factor moves the drive's limits"
                        if uset.supply_measured else "not measured (a board without the divider): the duty assumes the "
                        "nominal supply"))
    print("scenarios: step +-20 cm (5 s), square-wave edges +-20 cm (2.2 s level), tilt 0.1 rad (batch, estimator at the "
          f"measured tilt); push 0.2 N and kick 1 N s (scenario simulator, nominal + {uset.push_points} worst points)")
    t0 = time.perf_counter()

    def progress(done: int, total: int, ev: Any) -> None:
        s = ev.score
        sys.stderr.write(f"  candidate {done}/{total} {ev.candidate.name}: worst ratio {s[0]:.3g}, lost at {ev.falls}, "
                         f"failing at {s[1]} robots{'' if ev.nominal_ok else ', fails the nominal robot'}"
                         f"{'' if ev.precise else f', force row {ev.force_lsb:.0f} LSB'} "
                         f"({time.perf_counter() - t0:.0f} s)\n")
        sys.stderr.flush()

    evals = search(params, uset, args.candidates, seed=args.seed, progress=progress)
    wall = time.perf_counter() - t0
    best = evals[0]
    ship = next(e for e in evals if e.candidate.name == "shipped")
    print(f"\n{len(evals)} candidates in {wall:.0f} s, best first (nominal: passes on the design model; lsb: worst "
          f"error of the fixed-point force row, at most {FORCE_LSB_MAX:g}; worst: ratio to the limit, capped at a fall "
          "= 5; lost: robots where |phi| reaches phi_max; fails: robots failing a check):")
    print(f"  {'design':10s} {'q_x':>8s} {'q_xdot':>8s} {'q_phi':>8s} {'q_phidot':>8s} {'R':>6s} {'observer':>8s} "
          f"{'a_cmd':>6s} {'nominal':>7s} {'lsb':>4s} {'worst':>6s} {'lost':>5s} {'fails':>6s} {'mean':>6s}")
    for e in evals[:10]:
        c, s = e.candidate, e.score
        print(f"  {c.name:10s} {c.Q[0]:8.4g} {c.Q[1]:8.4g} {c.Q[2]:8.4g} {c.Q[3]:8.4g} {c.R:6.3g} {c.observer:8.3g} "
              f"{c.a_cmd:6.3g} {'PASS' if e.nominal_ok else 'FAIL':>7s} {e.force_lsb:4.0f} {s[0]:6.3g} {e.falls:5d} "
              f"{s[1]:6d} {s[2]:6.3g}")
    out: dict[str, Any] = {"params": str(params.source), "uncertainty": uset.source, "points": len(pts),
                           "supply_measured": uset.supply_measured,
                           "candidates": len(evals), "seed": args.seed, "wall_s": wall, "designs": {}}
    for label, e in (("best", best), ("shipped", ship)):
        rows = worst_rows(e, params)
        print(f"\nWorst case of the {label} design ({e.candidate.name}) over the set:")
        print(format_rows(rows))
        out["designs"][label] = {**e.candidate.as_dict(params), "score": list(e.score), "passes": e.passes,
                                 "nominal_ok": e.nominal_ok, "lost": e.falls,
                                 "worst": [{k: _jsonable(v) for k, v in r.items()} for r in rows],
                                 "worst_points": {f"{r['scenario']}/{r['constraint']}": e.points[r["point"]].as_dict(
                                     float(params.rate)) for r in rows if r["point"] >= 0}}
    export = best.candidate.as_dict(params)["export"]
    if best.passes:
        verdict = "meets the set"
        print(f"\nThe best design meets every constraint over the whole set: ship it ({export}).")
    elif best is ship or best.rank >= ship.rank:
        verdict = "shipped is best found"
        print("\nNo candidate meets every constraint over the whole set, and none beats the shipped default: keep it "
              "(docs/parameters.md, 'Robust design', says where it falls short).")
    else:
        verdict = "best found"
        print("\nNo candidate meets every constraint over the whole set. The best found beats the shipped default "
              f"(lost at {best.falls} robots against {ship.falls}, failing at {best.score[1]} against {ship.score[1]}); "
              f"by the rule 'otherwise ship the best found' it is the one to ship, with the worst case above: {export}, "
              "and its Q, R, observer and clamp as the defaults of host/design/discrete.py.")
    out["ship"] = bool(best.passes)
    out["verdict"] = verdict
    if json_path is not None:
        json_path.write_text(json.dumps(out, indent=2, default=float))
        print(f"wrote {json_path}")
    return 0
