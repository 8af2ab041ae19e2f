"""``make bench`` section: the worst case of the shipped design over the uncertainty set.

Per scenario and constraint (issue 15): the worst value over ``sim/uncertainty.toml`` (the
nominal robot, every vertex and the random points; the push at the nominal robot and the
worst points), the limit, how many robots fail, and where the worst is.  The evaluation is
:func:`host.design.robust.evaluate` -- the same as ``upright design --robust``.
"""

from __future__ import annotations

import math
import time
from typing import Any


def bench() -> dict[str, Any]:
    """Evaluate the shipped design over the default uncertainty set."""
    from host.design.robust import evaluate, load_uncertainty, shipped, worst_rows
    from sim.params import load_params

    params = load_params(None)
    uset = load_uncertainty()
    t0 = time.perf_counter()
    ev = evaluate(params, shipped(), uset)
    wall = time.perf_counter() - t0
    rows = []
    for r in worst_rows(ev, params):
        w = r["worst"]
        rows.append({"scenario": r["scenario"], "constraint": r["constraint"],
                     "worst": "never" if isinstance(w, float) and math.isinf(w) else w, "limit": r["limit"],
                     "verdict": r["verdict"], "robots_failing": f"{r['fails']}/{r['points']}", "at": r["at"]})
    score = ev.score
    notes = [
        f"shipped design {shipped().Q} R {shipped().R} clamp {shipped().a_cmd} m/s^2 over {uset.source}: "
        f"{len(ev.points)} robots, evaluated in {wall:.1f} s; robots with any failing check: {score[1]}",
        "step: +-20 cm from rest (5 s); square: its edges, settled within the 2.2 s level; tilt 0.1 rad (estimator "
        "from the measured tilt); push 0.2 N x 5 s in the scenario simulator at the nominal + worst points",
        "a fall shows as phi_max 1.571 (pi/2) and settle 'never'; docs/parameters.md 'Robust design'",
    ]
    return {"title": "Robust: worst case of the shipped design over the uncertainty set", "rows": rows,
            "notes": notes, "score": list(score), "robots": len(ev.points)}
