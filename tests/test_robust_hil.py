"""Robust design in HIL (issue 15 item 2): the shipped default, firmware in the loop on the
MicroPython unix port, on plants at points of the uncertainty set (``upright hil --plant``), agrees
with the robust evaluation's verdict and figures there -- one robot where it passes the 0.1 rad
tilt, one where the evaluation says it fails it (the supply 15 % low: the cart settles in ~4.5 s)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from host.design import robust as R
from sim.params import load_params

ROOT = Path(__file__).resolve().parents[1]

CORNERS = {
    "heavy_sticky": ({"inertia": 1.2, "friction": 2.0}, True),
    "low_supply": ({"supply": 0.85}, False),
}


@pytest.mark.parametrize("name", list(CORNERS))
def test_shipped_design_in_hil_at_a_corner_agrees_with_the_evaluation(tmp_path: Path, name: str) -> None:
    factors, passes = CORNERS[name]
    params = load_params(None)
    point = R.Point({**{k: 1.0 for k in R.FACTORS}, **factors}, round(params.delay * params.rate), False)
    ev = R.evaluate(params, R.shipped(), R.load_uncertainty(), points=[point], push=False)
    ok = all(ev.ratios("tilt", c)[0] <= 1.0 for c in R.CONSTRAINTS)
    assert ok is passes  # the evaluation's verdict at this robot
    plant = tmp_path / f"{name}.toml"
    plant.write_text(R.plant_toml(point, params))
    out = tmp_path / "hil.json"
    r = subprocess.run([sys.executable, "-m", "host.cli", "hil", "--scenario", "tilt_0p1", "--plant", str(plant),
                        "--json", str(out), "--no-plots", "--no-compare", "--quiet", "--out", str(tmp_path / "o")],
                       cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == (0 if passes else 1), r.stderr
    (run,) = json.loads(out.read_text())
    assert run["passed"] is passes
    assert run["accel_max"] == pytest.approx(ev.metrics["tilt"]["a_max"][0], rel=0.03)
    assert run["phi_max"] == pytest.approx(ev.metrics["tilt"]["phi_max"][0], abs=0.003)
    if not passes:  # the fixed-point firmware misses the settling as the evaluation says, by as much
        assert run["settle_s"] is not None and run["settle_s"] > params.t_settle
        assert run["settle_s"] == pytest.approx(ev.metrics["tilt"]["settle"][0], abs=0.3)
