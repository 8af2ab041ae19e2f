"""Plant model: analytic vs numeric linearisation, transfer functions, simulation accuracy."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from host.design import analysis
from host.cli.main import main
from sim.params import load_params
from sim.plant import dynamics, linear_model, make_nlsys, reduced_model, simulate


@pytest.fixture(scope="module")
def params():  # noqa: ANN201
    return load_params()


def test_analytic_matches_numeric_linearisation(params) -> None:  # noqa: ANN001
    A, B, C, D = linear_model(params)
    lin = make_nlsys(params).linearize(np.zeros(4), np.zeros(1))
    np.testing.assert_allclose(lin.A, A, atol=1e-7)
    np.testing.assert_allclose(lin.B, B, atol=1e-7)
    np.testing.assert_allclose(lin.C, C, atol=1e-12)


def test_linearisation_at_other_parameters(params) -> None:  # noqa: ANN001
    p = params.replace(M=1.3, b=0.5, m_cam=0.3)
    A, B, _, _ = linear_model(p)
    lin = make_nlsys(p).linearize(np.zeros(4), np.zeros(1))
    np.testing.assert_allclose(lin.A, A, atol=1e-7)
    np.testing.assert_allclose(lin.B, B, atol=1e-7)


def test_nonlinear_terms_matter_away_from_upright(params) -> None:  # noqa: ANN001
    A, B, _, _ = linear_model(params)
    x = np.array([0.0, 0.5, 0.8, 2.0])
    f = dynamics(0.0, x, np.array([1.0]), params.physical)
    assert np.max(np.abs(f - (A @ x + B[:, 0]))) > 0.5


def test_dynamics_broadcasts_over_a_batch(params) -> None:  # noqa: ANN001
    X = np.random.default_rng(1).normal(size=(4, 7)) * 0.2
    U = np.linspace(-1, 1, 7)
    batch = dynamics(0.0, X, U, params.physical)
    for i in range(7):
        np.testing.assert_allclose(batch[:, i], dynamics(0.0, X[:, i], np.array([U[i]]), params.physical), rtol=1e-12)


def test_transfer_functions_cleaned(params) -> None:  # noqa: ANN001
    tfs = analysis.transfer_functions(params)
    num = np.squeeze(tfs["phi"].num[0][0])
    den = np.squeeze(tfs["phi"].den[0][0])
    assert len(num) == 2 and num[1] == 0.0  # 3.374 s, spurious terms removed
    assert len(den) == 4 and den[0] == 1.0
    # x/F keeps its pole at the origin (the cart is an integrator)
    assert np.squeeze(tfs["x"].den[0][0])[-1] == 0.0
    poles = np.sort(tfs["phi"].poles().real)
    np.testing.assert_allclose(poles, [-4.8787, -0.13964, 4.8540], atol=2e-4)


def test_single_sensor_observability(params) -> None:  # noqa: ANN001
    res = {(o.model, o.sensor): o for o in analysis.single_sensor_observability(params)}
    assert res["full", "x"].observable
    assert not res["full", "phi"].observable  # translation invariance: phi alone cannot see x
    assert all(res["reduced", s].observable for s in ("xdot", "phi", "phidot"))
    # the cart speed gives the largest observability ellipsoid (report Table 2.3)
    vols = {s: res["reduced", s].volume for s in ("xdot", "phi", "phidot")}
    assert max(vols, key=vols.get) == "xdot"


def test_gramian_matches_quadrature() -> None:
    A = np.array([[0.0, 1.0], [2.0, -0.3]])  # unstable
    C = np.array([[1.0, 0.0]])
    T = 0.7
    W = analysis.observability_gramian(A, C, T)
    from scipy.linalg import expm

    from scipy.integrate import simpson

    ts = np.linspace(0, T, 201)
    vals = np.array([expm(A.T * t) @ C.T @ C @ expm(A * t) for t in ts])
    np.testing.assert_allclose(W, simpson(vals, x=ts, axis=0), rtol=1e-6)


def test_reduced_model_is_lower_right_block(params) -> None:  # noqa: ANN001
    A, B, _, _ = linear_model(params)
    Ar, Br = reduced_model(params)
    np.testing.assert_array_equal(Ar, A[1:, 1:])
    np.testing.assert_array_equal(Br, B[1:])


def test_simulate_cli_open_loop_matches_accurate_ode(tmp_path: Path, params) -> None:  # noqa: ANN001
    out = tmp_path / "out.csv"
    assert main(["simulate", "--open-loop", "--phi0", "0.05", "--duration", "0.6", "--csv", str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    assert list(rows[0]) == ["t", "x", "xdot", "phi", "phidot", "force"]
    t = np.array([float(r["t"]) for r in rows])
    phi = np.array([float(r["phi"]) for r in rows])
    ref = solve_ivp(
        lambda tt, x: dynamics(tt, x, np.zeros(1), params.physical),
        (0, 0.6),
        [0, 0, 0.05, 0],
        method="DOP853",
        rtol=1e-12,
        atol=1e-12,
        t_eval=t,
    )
    mask = np.abs(ref.y[2]) < 1.0
    assert mask.sum() > 500 and abs(phi[-1]) > 0.3  # it really fell
    assert np.max(np.abs(phi[mask] - ref.y[2][mask])) < 1e-4


def test_simulate_force_profile_and_limit(params) -> None:  # noqa: ANN001
    res = simulate(params, [0, 0, 0, 0], 0.2, controller=lambda t, x: 100.0, u_limit=3.0, force=lambda t: 0.5)
    assert np.allclose(res["force"], 3.5)
    with pytest.raises(ValueError):
        simulate(params, [0, 0, 0, 0], 0.1, dt=0.0)
