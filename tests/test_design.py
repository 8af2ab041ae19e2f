"""Design toolkit: the report's numbers, and every design balancing the nonlinear plant."""

from __future__ import annotations

import control as ct
import numpy as np
import pytest

from host.design import controllers as design
from host.cli.report import REPORT, deviation, seed_numbers
from sim.params import load_params
from sim.plant import linear_model, simulate


@pytest.fixture(scope="module")
def params():  # noqa: ANN201
    return load_params()


@pytest.fixture(scope="module")
def ours(params):  # noqa: ANN001, ANN201
    return seed_numbers(params)


# Each of the report's numbers, recomputed, must agree to the digits the report prints: within
# half a unit of its last printed digit (absolute, per entry).  Measured when set: every entry
# inside its bound (largest: k_place[2] 199.82415 vs 199.8242, 4.9e-5 of 5e-5; eigenvalue
# -0.13964 vs -0.1396; zeta 0.62658 vs 0.627).  docs/parameters.md quotes the deviations.
HALF_DIGIT = {
    "eigenvalues": 5e-5,  # 4 decimals
    "tf_phi_num": [5e-5, 1e-12],  # 3.3745 s + 0 (exact zero)
    "tf_phi_den": [1e-12, 5e-5, 5e-3, 5e-4],  # s^3 + 0.1644 s^2 - 23.68 s - 3.307
    "det_wr": 0.5,  # 1.2453e4
    "rank_wo": 0,
    "zeta": 5e-4,  # 0.627
    # 7.59 where the exact value is 7.5999: the report cut the digits off instead of rounding,
    # so one unit of the last digit (measured 0.0099)
    "omega": 1e-2,
    "k_place": 5e-5,  # 4 decimals
    "k_lqr": 5e-5,  # 4 decimals
    "observer_poles": 1e-9,  # placed exactly at -47.74 ... -50.74 (measured 2e-13)
    # read off a Nyquist plot as "about 3.7": one unit of that digit (exact boundary 3.6150,
    # 0.085 off, 2.3 %); the reading, not the computation, sets this bound
    "critical_gain": 0.1,
}


@pytest.mark.parametrize("key", list(REPORT))
def test_report_number_within_its_printed_digits(ours, key: str) -> None:  # noqa: ANN001
    assert set(HALF_DIGIT) == set(REPORT)
    got, want = np.atleast_1d(np.asarray(ours[key], float)), np.atleast_1d(np.asarray(REPORT[key][1], float))
    assert got.shape == want.shape, (key, got, want)
    tol = np.broadcast_to(np.asarray(HALF_DIGIT[key], float), want.shape)
    assert np.all(np.abs(got - want) <= tol * (1 + 1e-9)), (key, got, want, np.abs(got - want))
    # the relative figure docs/parameters.md prints stays what the table says (< 1 %, the
    # critical gain < 3 %)
    assert deviation(ours[key], REPORT[key][1]) < (0.03 if key == "critical_gain" else 0.01)


def test_deviation_detects_a_wrong_number() -> None:
    assert deviation([1.0, 2.0], [1.0, 2.1]) > 0.04
    assert deviation([1.0], [1.0, 2.0]) == float("inf")


def test_spec_to_poles() -> None:
    zeta, omega = design.zeta_omega_from_spec(0.08, 0.84)
    poles = design.dominant_poles(zeta, omega)
    # the dominant pair has the requested damping and 2 % settling time 4/(zeta omega)
    assert abs(-poles[0].real / abs(poles[0]) - zeta) < 1e-12
    assert 4 / -poles[0].real == pytest.approx(0.84)
    assert np.all(poles[2:].real < 2 * poles[0].real)
    with pytest.raises(ValueError):
        design.zeta_omega_from_spec(1.5, 1.0)


def test_place_gives_requested_poles(params) -> None:  # noqa: ANN001
    A, B, _, _ = linear_model(params)
    K = design.place_gain(params)
    got = np.sort_complex(np.linalg.eigvals(A - B @ K[None, :]))
    np.testing.assert_allclose(got, np.sort_complex(np.array(design.REPORT_PLACE_POLES)), atol=1e-8)


def test_observer_ten_times_faster(params) -> None:  # noqa: ANN001
    A, B, C, _ = linear_model(params)
    K = design.place_gain(params)
    L, poles = design.observer_gain(params, K)
    got = np.sort(np.linalg.eigvals(A - L @ C).real)
    np.testing.assert_allclose(got, np.sort(poles.real), atol=1e-6)
    slowest_ctrl = np.min(np.abs(np.linalg.eigvals(A - B @ K[None, :]).real))
    assert np.max(got) == pytest.approx(-10 * slowest_ctrl)


def test_precompensator_gives_unit_dc_gain(params) -> None:  # noqa: ANN001
    A, B, _, _ = linear_model(params)
    K = design.lqr_gain(params)
    kr = design.precompensator(params, K)
    dc = (np.array([[1, 0, 0, 0]]) @ np.linalg.solve(-(A - B @ K[None, :]), B * kr))[0, 0]
    assert dc == pytest.approx(1.0)


@pytest.mark.parametrize("name", ["place", "lqr", "place-observer", "lqr-observer", "pid", "loopshape"])
def test_each_design_stabilises_nonlinear_plant_from_0p1_rad(params, name: str) -> None:  # noqa: ANN001
    res = simulate(params, [0, 0, 0.1, 0], 6.0, controller=design.make_controller(params, name), dt=1e-3, substeps=2)
    late = res["t"] > 5.0
    assert np.max(np.abs(res["phi"][late])) < 1e-3
    assert np.max(np.abs(res["phi"])) < 0.5


def test_lqr_search_finds_weights_meeting_constraints(params) -> None:  # noqa: ANN001
    ranked = design.lqr_weight_search(params, q_x=(0.2, 5.4), q_phi=(0.1,))
    (best_w, best), (_, report_lqr) = ranked
    assert best_w == (0.2, 0.1) and best.ok
    # the report's weights violate the 5 m/s^2 acceleration limit on a 20 cm step
    assert not report_lqr.checks["accel"] and report_lqr.checks["phi"]


def test_nyquist_and_gang_of_four(params) -> None:  # noqa: ANN001
    s = ct.tf("s")
    low = design.analyse_loop(params, (s + 1) ** 2 / s)
    assert (low.open_loop_rhp, low.encirclements, low.closed_loop_rhp, low.stable) == (1, 1, 2, False)
    final = design.analyse_loop(params, design.loop_controller(20, 1, 10))
    assert (final.open_loop_rhp, final.encirclements, final.closed_loop_rhp, final.stable) == (1, -1, 0, True)
    # S, T and PS are stable; CS keeps the controller's integrator (cancelled against the
    # plant's zero at s = 0) and is improper: the report's "two of four unstable" finding
    assert all(final.gang[k]["stable"] for k in ("S", "T", "PS"))
    assert not final.gang["CS"]["stable"] and final.gang["CS"]["poles_at_origin"] == 1
    assert not final.gang["CS"]["proper"]
    assert 0.99 < final.ms < 2.0 and final.mt < 2.0  # S -> 1 at high frequency


def test_critical_gain_is_the_stability_boundary(params) -> None:  # noqa: ANN001
    s = ct.tf("s")
    kc = design.critical_gain(params, (s + 1) ** 2 / s)
    assert not design.analyse_loop(params, 0.98 * kc * (s + 1) ** 2 / s).stable
    assert design.analyse_loop(params, 1.02 * kc * (s + 1) ** 2 / s).stable
