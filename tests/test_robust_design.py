"""Robust design (issue 15 item 2): ``upright design --robust`` on a tiny budget, its worst case
reproduced by a direct simulation of that corner, and bad uncertainty files named by key."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from host.design import robust as R
from sim.params import load_params

ROOT = Path(__file__).resolve().parents[1]

TINY = """
inertia = [0.6, 1.0]
cart_mass = [1.0, 1.2]
pendulum_mass = [1.0, 1.0]
friction = [1.0, 1.0]
supply = [0.85, 0.85]
motor_constant = [1.0, 1.0]
delay = [0.01, 0.02]
random = 1
seed = 3
push_points = 1
"""


def _upright(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "host.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=600)


@pytest.mark.slow
def test_robust_command_tiny_budget_reproduced_by_direct_simulation(tmp_path: Path) -> None:
    unc = tmp_path / "tiny.toml"
    unc.write_text(TINY)
    out = tmp_path / "robust.json"
    r = _upright("design", "--robust", "--uncertainty", str(unc), "--candidates", "2", "--json", str(out))
    assert r.returncode == 0, r.stderr
    assert "Worst case of the best design" in r.stdout and "Worst case of the shipped design" in r.stdout
    data = json.loads(out.read_text())
    assert data["points"] == 1 + 8 + 1  # nominal, 2^3 vertices, one random point
    best = data["designs"]["best"]
    rows = best["worst"]
    # every scenario and constraint (the kick's acceleration is none: a Dirac kick, sim/scenarios/impulse_kick.toml)
    want = {(s, c) for s in R.SCENARIOS for c in R.CONSTRAINTS} - {("kick", "a_max")}
    assert {(w["scenario"], w["constraint"]) for w in rows} == want
    for w in rows:  # every row printed with its verdict
        assert w["verdict"] in ("PASS", "FAIL")
        assert f"{w['scenario']}" in r.stdout
    # every worst case of the batch scenarios, reproduced by the scenario simulator at its corner
    params = load_params(None)
    cand = R.Candidate("best", tuple(best["Q"]), best["R"], best["observer"], best["a_cmd"])
    ctrl = cand.controller(params)
    for row in rows:
        s, c = row["scenario"], row["constraint"]
        if s in R.FORCE_SCENARIOS:
            continue  # the push and the kick are run in the scenario simulator already
        corner = best["worst_points"][f"{s}/{c}"]
        point = R.Point({k: corner[k] for k in R.FACTORS}, round(corner["delay_s"] * params.rate), corner["vertex"])
        signs = (1.0, -1.0) if s != "tilt" else (1.0,)
        runs = [R.simulate_corner(s, point, params, ctrl, sign, supply_measured=data["supply_measured"]) for sign in signs]
        got = max(r[R.CONSTRAINTS.index(c)] for r in runs)
        want = math.inf if row["worst"] == "never" else row["worst"]
        if c == "settle":
            assert got == pytest.approx(want, abs=0.05), (s, c, corner)
        else:  # the batch takes |xddot| at every RK4 stage, the scenario log once per tick
            assert got == pytest.approx(want, rel=0.05, abs=1e-3), (s, c, corner)


def test_evaluation_agrees_with_the_scenario_simulator_on_settling() -> None:
    params = load_params(None)
    uset = R.uncertainty_from_dict({"random": 0}, "<test>", R.load_uncertainty())
    soft = {k: 1.0 for k in R.FACTORS}
    pts = [uset.points(params.rate, params.delay)[0], R.Point({**soft, "inertia": 0.8}, 5, False),
           R.Point({**soft, "inertia": 0.7}, 5, False)]
    ev = R.evaluate(params, R.shipped(), uset, push=False, points=pts)
    ctrl = R.shipped().controller(params)
    # tilt and square at the nominal robot and at inertia x0.8.  (At x0.7 the two simulators'
    # tilt traces agree within a quarter ADC count, but a one-count limit cycle crosses the
    # settling band's edge at 2.2 s in one and at 3.4 s in the other: the settling time is
    # discontinuous there, docs/parameters.md, Robust design.)
    for i, p in enumerate(pts[:2]):
        for kind in ("tilt", "square"):
            phi, acc, settle = R.simulate_corner(kind, p, params, ctrl)
            assert ev.metrics[kind]["settle"][i] == pytest.approx(settle, abs=0.05), (kind, i)
            assert ev.metrics[kind]["phi_max"][i] == pytest.approx(phi, rel=0.02), (kind, i)
            assert ev.metrics[kind]["a_max"][i] == pytest.approx(acc, rel=0.05), (kind, i)
    # the step both ways, and the soft pendulum of the issue: the shipped design misses 2.5 s
    # on the step at inertia x0.7, not at nominal
    for i in (0, 2):
        settle = max(R.simulate_corner("step", pts[i], params, ctrl, sign)[2] for sign in (1.0, -1.0))
        assert ev.metrics["step"]["settle"][i] == pytest.approx(settle, abs=0.05), i
    assert ev.metrics["step"]["settle"][0] < params.t_settle < ev.metrics["step"]["settle"][2]


@pytest.mark.parametrize("text, key", [
    ("inertia = [0.5, 1.2]\nbogus = 1\n", "bogus"),
    ("friction = [2.0, 0.5]\n", "friction"),
    ("supply = 1.1\n", "supply"),
    ("delay = [0.0, 0.015]\n", "delay"),
    ("delay = [0.0, 0.0155]\n", "delay"),
    ("random = -1\n", "random"),
    ("supply_measured = 1\n", "supply_measured"),
])
def test_bad_uncertainty_file_names_the_key(tmp_path: Path, text: str, key: str) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(text)
    if key == "delay":  # 15 ms is 7.5 ticks at 500 Hz: refused when the points are made (the rate is the robot's)
        with pytest.raises(R.UncertaintyError) as ei:
            R.load_uncertainty(f).points(500.0, 0.01)
    else:
        with pytest.raises(R.UncertaintyError) as ei:
            R.load_uncertainty(f)
    assert ei.value.key == key


@pytest.mark.slow
def test_bad_uncertainty_file_on_the_command_line(tmp_path: Path) -> None:
    f = tmp_path / "bad.toml"
    f.write_text("motor_constant = [0.9, 1.1]\ninertai = [0.5, 1.2]\n")
    r = _upright("design", "--robust", "--uncertainty", str(f))
    assert r.returncode == 2
    assert "inertai" in r.stderr and len(r.stderr.strip().splitlines()) == 1
