"""One JSON object per HIL scenario (``upright hil --json FILE``): verdict, metrics, loop timing.

Works for every kind of run (virtual, board, emulated).  ``tick_us_mean``/``tick_us_max`` are the
firmware's whole loop iteration where the run measured it (the emulated RP2040: emulated cycles
at 125 MHz, ``tick_source`` says so), else the firmware's own control-step time from telemetry.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Sequence

from host.hil.results import HilRun

__all__ = ["scenario_record", "write_records"]


def scenario_record(run: HilRun) -> dict[str, Any]:
    """One scenario's JSON object (``upright hil --json``): verdict, metrics, loop timing."""
    s = run.summary()
    m = s.metrics
    st = run.stats

    def num(v: Any) -> Any:
        try:
            f = float(v)
        except (TypeError, ValueError):
            return None
        return f if math.isfinite(f) else None

    err = run.phi_error()
    return {
        "name": run.name,
        "mode": run.mode,
        "link": run.link,
        "passed": bool(s.as_expected),
        "checks": {c.name: {"status": c.status, "expected": c.expected, "value": num(c.value)} for c in s.checks},
        "phi_max": num(m.peak_phi),
        "settle_s": num(m.settling_time),
        "accel_max": num(m.peak_xddot),
        "force_max": num(m.peak_force),
        "dphi_vs_float": num(err),
        "tick_us_mean": num(st.get("tick_us_mean", st.get("fw_step_us_mean"))),
        "tick_us_max": num(st.get("tick_us_max", st.get("fw_step_us_max"))),
        "tick_source": "loop iteration, emulated cycles" if "tick_us_mean" in st else "firmware step_us (telemetry)",
        "period_us": num(st.get("period_us", 1e6 / run.params.rate)),
        "fw_step_us_mean": num(st.get("fw_step_us_mean")),
        "fw_step_us_max": num(st.get("fw_step_us_max")),
        "ticks": st.get("ticks"),
        "wall_s": num(run.wall_s),
        "emu_speed": num(st.get("emu_speed")),
    }


def write_records(runs: Sequence[HilRun], path: str | Path) -> Path:
    """Write the runs' :func:`scenario_record` objects as a JSON list to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps([scenario_record(r) for r in runs], indent=1) + "\n")
    return path
