"""One plant-equation module (issue 25 item 3): every simulator takes the equations of motion from
``sim/plant.py``, and the compiled batch kernel's specialised copy gives exactly their values.

``sim.plant.accelerations`` is the one solution of the two equations; :func:`sim.plant.dynamics`
(the numpy batch reference), :class:`sim.plantsim.PlantSim` (ideal and realistic plant) and the
catch study's split forms are checked against it value for value, and so are the kernel's two
RK4 stages (``sim.batch_kernel._stage`` and ``_stage_real``: sliding, stuck) on random lanes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim import batch_kernel as BK
from sim.params import load_params
from sim.plant import (accelerations, dynamics, force_for_xddot, phiddot_given_xddot, pivot_fixed_phiddot,
                       xddot_affine)
from sim.plantsim import PlantSim
from sim.scenario import scenario_from_dict


def _lanes(n: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    p = load_params()
    f = rng.uniform(0.5, 1.5, (5, n))
    M, m, L, I, b = p.M * f[0], p.m * f[1], np.full(n, p.L), p.I * f[2], p.b * f[3]
    mL = m * L
    return {"F": rng.uniform(-20, 20, n), "xd": rng.uniform(-2, 2, n), "phi": rng.uniform(-1.6, 1.6, n),
            "phid": rng.uniform(-8, 8, n), "Mt": M + m, "mL": mL, "J": I + m * L * L, "b": b, "mLg": mL * p.g,
            "M": M, "m": m, "L": L, "I": I, "g": np.full(n, p.g)}


def _bits(a: np.ndarray) -> np.ndarray:
    return np.asarray(a, dtype=np.float64).view(np.int64)


def test_dynamics_is_the_accelerations_of_the_one_module() -> None:
    v = _lanes(4096, 1)
    X = np.array([np.zeros_like(v["xd"]), v["xd"], v["phi"], v["phid"]])
    s, c = np.sin(v["phi"]), np.cos(v["phi"])
    xdd, phidd = accelerations(v["F"], v["xd"], v["phid"], s, c, v["Mt"], v["mL"], v["J"], v["b"], v["mLg"])
    for i in range(0, 4096, 97):  # dynamics takes one robot's mapping: one lane at a time
        phys = {k: float(v[k][i]) for k in ("M", "m", "L", "I", "b", "g")}
        d = dynamics(0.0, X[:, i:i + 1], v["F"][i:i + 1], phys)
        assert _bits(d[1]) == _bits(xdd[i:i + 1]) and _bits(d[3]) == _bits(phidd[i:i + 1])
    # the equations hold: both residuals vanish (to rounding)
    r1 = v["Mt"] * xdd + v["b"] * v["xd"] - v["mL"] * c * phidd + v["mL"] * v["phid"] ** 2 * s - v["F"]
    r2 = v["J"] * phidd - v["mLg"] * s - v["mL"] * c * xdd
    assert np.max(np.abs(r1)) < 1e-9 and np.max(np.abs(r2)) < 1e-9
    # the catch study's split forms are the same first equation and the second solved for the tilt
    a0, gain = xddot_affine(v["xd"], v["phid"], s, c, v["Mt"], v["mL"], v["J"], v["b"], v["g"])
    assert np.allclose(a0 + gain * v["F"], xdd, rtol=1e-12, atol=1e-9)
    assert np.allclose(force_for_xddot(xdd, v["xd"], v["phid"], s, c, v["Mt"], v["mL"], v["J"], v["b"], v["g"]),
                       v["F"], rtol=1e-9, atol=1e-9)
    assert np.allclose(phiddot_given_xddot(xdd, s, c, v["mL"], v["J"], v["g"]), phidd, rtol=1e-12, atol=1e-9)


def test_the_scenario_simulator_uses_the_one_module() -> None:
    p = load_params()
    sc = scenario_from_dict({"name": "eq", "duration": 1.0})
    v = _lanes(64, 2)
    phys = p.physical
    for real in (False, True):
        pr = p.replace(**{"cart.coulomb": 0.3, "cart.stiction": 0.5}) if real else p
        sim = PlantSim(pr, sc)
        sim._stuck = False  # sliding
        assert sim._mL == phys["m"] * phys["L"]
        for i in range(64):
            x = [0.0, float(v["xd"][i]), float(v["phi"][i]), float(v["phid"][i])]
            d = sim._rhs(x, 0.0, 0.0)
            F = sim._drive_force(0.0, x[1]) - (sim._fc * sim._dir if real else 0.0)
            want = accelerations(F, x[1], x[3], math.sin(x[2]), math.cos(x[2]), sim._M + sim._m, sim._mL, sim._J,
                                 sim._b, sim._mL * sim._g)
            assert (d[1], d[3]) == want
        if real:
            sim._stuck = True
            d = sim._rhs([0.0, 0.0, 0.2, 0.0], 0.0, 0.0)
            assert d[1] == 0.0 and d[3] == pivot_fixed_phiddot(math.sin(0.2), sim._mL * sim._g, sim._J)


@pytest.mark.slow
@pytest.mark.skipif(not BK.AVAILABLE, reason="numba not installed")
@pytest.mark.parametrize("stage", ["_stage", "_stage_real"])
def test_the_batch_kernels_copy_gives_the_one_modules_values(stage: str) -> None:
    # the kernel's RK4 stage on 16 random lanes, drive="force" (the held force of row _US), no clip
    v = _lanes(BK.LANES, 3)
    S = np.zeros((BK._NROWS, BK.LANES))
    S[BK._Y1], S[BK._Y2], S[BK._Y3], S[BK._US] = v["xd"], v["phi"], v["phid"], v["F"]
    S[BK._MM], S[BK._J], S[BK._ML], S[BK._B], S[BK._MLG] = v["Mt"], v["J"], v["mL"], v["b"], v["mLg"]
    S[BK._MMJ] = v["Mt"] * v["J"]  # as run_chunk precomputes it
    stuck = np.arange(BK.LANES) % 3 == 0
    if stage == "_stage_real":
        S[BK._FRIC] = 1.0
        S[BK._FF] = 0.4 * np.where(v["xd"] >= 0, 1.0, -1.0)
        S[BK._STK] = stuck
    kr = BK._K2
    getattr(BK, stage)(S, kr, False, False, 0.0)
    s, c = S[BK._SN], S[BK._CS]  # the kernel's own sincos (checked against numpy elsewhere)
    assert np.array_equal(s, [math.sin(y) for y in v["phi"]]) and np.array_equal(c, [math.cos(y) for y in v["phi"]])
    F = v["F"] - S[BK._FF] if stage == "_stage_real" else v["F"]
    xdd, phidd = accelerations(F, v["xd"], v["phid"], s, c, v["Mt"], v["mL"], v["J"], v["b"], v["mLg"])
    if stage == "_stage_real":
        xdd = np.where(stuck, 0.0, xdd)
        phidd = np.where(stuck, pivot_fixed_phiddot(s, v["mLg"], v["J"]), phidd)
    assert np.array_equal(_bits(S[kr + 1]), _bits(xdd)) and np.array_equal(_bits(S[kr + 3]), _bits(phidd))
    assert np.array_equal(S[kr], v["xd"]) and np.array_equal(S[kr + 2], v["phid"]) and np.array_equal(S[kr + 4], v["F"])
