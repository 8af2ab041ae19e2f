"""``make bench`` section: the worst case of the shipped design over the uncertainty set.

Per scenario and constraint (issue 15): the worst value over ``sim/uncertainty.toml`` (the
nominal robot, every vertex and the random points; the push and the kick at the nominal robot
and the worst points), the limit, how many robots fail, and where the worst is -- on the
default board, which measures its motor supply (``supply_measured``), and on a board without
the supply divider.  The evaluation is :func:`host.design.robust.evaluate` -- the same as
``upright design --robust``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any


def bench() -> dict[str, Any]:
    """Evaluate the shipped design over the default uncertainty set, supply measured or not."""
    from host.design.robust import evaluate, load_uncertainty, shipped, worst_rows
    from sim.params import load_params

    params = load_params(None)
    base = load_uncertainty()
    c = shipped()
    rows = []
    notes = [f"shipped design Q {c.Q} R {c.R:g} observer {c.observer:g} clamp {c.a_cmd:g} m/s^2 over {base.source}"]
    scores = {}
    for measured in (True, False):
        uset = dataclasses.replace(base, supply_measured=measured)
        board = "supply measured" if measured else "no divider"
        t0 = time.perf_counter()
        ev = evaluate(params, c, uset)
        wall = time.perf_counter() - t0
        for r in worst_rows(ev, params):
            w = r["worst"]
            rows.append({"board": board, "scenario": r["scenario"], "constraint": r["constraint"],
                         "worst": "never" if isinstance(w, float) and math.isinf(w) else w, "limit": r["limit"],
                         "verdict": r["verdict"], "robots_failing": f"{r['fails']}/{r['points']}", "at": r["at"]})
        scores[board] = [*ev.score, ev.falls]
        notes.append(f"{board}: {len(ev.points)} robots in {wall:.1f} s; any failing check at {ev.score[1]}, "
                     f"pendulum lost at {ev.falls}; nominal robot {'PASS' if ev.nominal_ok else 'FAIL'}")
    notes += [
        "supply measured: the default board's divider (firmware/board.py VSUP_ADC_PIN), the duty scaled by it; "
        "no divider: the duty assumes the nominal supply",
        "step: +-20 cm from rest (5 s); square: its edges, settled within the 2.2 s level; tilt 0.1 rad (estimator "
        "from the measured tilt); kick 1 N s at rest (its acceleration is no constraint); push 0.2 N x 5 s in the "
        "scenario simulator at the nominal + worst points",
        "a fall shows as phi_max 1.571 (pi/2) and settle 'never'; docs/parameters.md 'Robust design'",
    ]
    return {"title": "Robust: worst case of the shipped design over the uncertainty set", "rows": rows,
            "notes": notes, "score": scores, "robots": len(ev.points)}
