"""One uncertainty model: the sweep's Monte Carlo and the robust box both draw through
:class:`host.design.uncertainty.Axis`, and their numbers are those of the code before the merge.

``tests/data/uncertainty_draws.json`` was written by the draw code as it stood before the axes
(commit cba71df, the sweep's own formulas in ``sample_runs`` and the box's ``lo + (hi - lo) r``):
for three sweep configurations the drawn table, initial states, batch values and delay ticks;
for the default and the realistic box every random point.  Equality is exact (JSON keeps a
float's 17 digits), except where numpy's vectorised ``exp``/``log`` (the log-uniform law) run:
their SIMD kernels differ by the CPU (AVX-512 against AVX2), and a CI machine drew the friction
factor one ulp away (0.08210255526317717 against ...715).  Those numbers are compared to within
:data:`MAX_ULP` units in the last place -- a change of formula moves them by far more.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from host.design.uncertainty import UNCERTAINTY_REALISTIC, Axis, UncertaintyError, load_uncertainty, scaled_values
from host.studies.sweep import Design, SweepConfig, Uncertainty, sample_runs
from sim.params import load_params

MAX_ULP = 4
"""The last-place units a float may differ by: numpy's SIMD exp/log are not the same bits on every CPU."""

DRAWS = json.loads((Path(__file__).parent / "data" / "uncertainty_draws.json").read_text())


@pytest.fixture(scope="module")
def p():
    return load_params()


@pytest.mark.parametrize("case", DRAWS["sweep"], ids=lambda c: c["case"])
def test_the_sweeps_draw_is_the_number_for_number_the_draw_before_the_axes(p, case) -> None:
    u = case["uncertainty"]
    un = Uncertainty(mass=u["mass"], inertia=u["inertia"], friction=tuple(u["friction"]), motor=u["motor"],
                     delay=tuple(u["delay"]), tilt=u["tilt"])
    designs = (Design("a"), Design("b", R=0.1)) if case["per_design"] else ()
    cfg = SweepConfig(params=p, uncertainty=un, seed=case["seed"], designs=designs, per_design=case["per_design"])
    runs, table = sample_runs(cfg, case["start"], case["stop"])
    old = case["table"]
    for k, v in table.items():
        want = old[k]
        if k == "design":
            assert [str(x) for x in v] == want, k
        else:
            _same_floats(v, want, k)
    _same_floats(runs.x0, old["x0"], "x0")
    assert runs.delay_ticks.tolist() == old["delay_ticks"]
    assert sorted(runs.values) == sorted(old["values"])
    for k, v in runs.values.items():
        _same_floats(v, old["values"][k], k)


def _same_floats(got, want, what: str) -> None:
    """Equal shapes and every number within :data:`MAX_ULP` of the recorded one."""
    g, w = np.asarray(got, float), np.asarray(want, float)
    assert g.shape == w.shape, what
    np.testing.assert_array_max_ulp(g, w, maxulp=MAX_ULP)


@pytest.mark.parametrize("case", DRAWS["points"], ids=lambda c: str(c["file"]))
def test_the_boxs_random_points_are_the_points_before_the_axes(p, case) -> None:
    path = None if case["file"] is None else UNCERTAINTY_REALISTIC.with_name(case["file"])
    pts = load_uncertainty(path).points(p.rate, p.delay)
    rand = [pt for pt in pts if not pt.vertex][1:]
    assert len(pts) == case["count"]
    assert [{"factors": dict(q.factors), "delay_ticks": q.delay_ticks, "realism": dict(q.realism)} for q in rand] \
        == case["random"]


def test_an_axis_draws_by_its_law() -> None:
    u = np.array([0.0, 0.5, 0.999999])
    assert Axis.uniform("cart_mass", 0.8, 1.2).draw(u).tolist() == pytest.approx([0.8, 1.0, 1.2], abs=1e-6)
    assert Axis.symmetric("tilt", 0.0, 0.03).draw(u).tolist() == pytest.approx([-0.03, 0.0, 0.03], abs=1e-6)
    lg = Axis.log_uniform("friction", 0.5, 2.0).draw(u)
    assert lg.tolist() == pytest.approx([0.5, 1.0, 2.0], abs=1e-5)  # the middle of a log range is its geometric mean
    assert Axis.symmetric("motor_constant", 1.0, 0.1).bounds == pytest.approx((0.9, 1.1))
    with pytest.raises(UncertaintyError, match="friction"):
        Axis.log_uniform("friction", 0.0, 2.0)
    with pytest.raises(UncertaintyError, match="cart_mass: unknown law"):
        Axis("cart_mass", "gaussian", 1.0, 0.1)


def test_a_coupled_axis_scales_by_the_axis_it_rides_on(p) -> None:
    ax = Uncertainty().axes()
    assert ax["inertia"].times == "pendulum_mass" and ax["cart_mass"].times == ""
    v = scaled_values(p, ax, {"cart_mass": 1.0, "pendulum_mass": 1.5, "inertia": 2.0, "friction": 1.0,
                              "resistance": 1.0, "motor_constant": 1.0})
    assert v["I"] == pytest.approx(3.0 * p.I) and v["m_cam"] == pytest.approx(1.5 * p.m_cam)
    assert "V_supply" not in v  # no supply axis in the sweep: the robot's value
    box = load_uncertainty().axes()
    assert box["inertia"].times == "" and box["inertia"].law == "uniform"  # the box's inertia is independent
    assert math.isclose(box["inertia"].bounds[0], load_uncertainty().factors["inertia"][0])
