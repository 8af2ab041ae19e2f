"""The discrete controller (host/design/discrete.py) against the nonlinear plant with delay and saturation.

Bounds: the angle is judged in ADC counts of the potentiometer (PHI_COUNT, 1.15 mrad; the
loops here run on quantised sensors), the cart in encoder counts (X_COUNT, 0.157 mm); each
assertion says what was measured when it was set.
"""

from __future__ import annotations

import control as ct
import numpy as np
import pytest

from host.design.discrete import (A_CMD_DEFAULT, Q_DEFAULT, Q_REPORT, R_DEFAULT, R_REPORT, controller_ss, delay_steps,
                           discretise, force_clamp, force_limit, simulate_loop)
from sim.params import load_params
from sim.plant import linear_model


@pytest.fixture(scope="module")
def params():
    return load_params()


_P = load_params()
PHI_COUNT = _P.pot_range / 2**_P.adc_bits  # one ADC count of the angle, rad
X_COUNT = 2 * np.pi * _P.r_wheel / _P.enc_cpr  # one encoder count of the cart, m


@pytest.fixture(scope="module")
def ctrl(params):
    return controller_ss(params)


def test_shapes_and_delay(params, ctrl) -> None:
    assert ctrl.delay_steps == 5 == delay_steps(params)
    n = 4 + 5
    assert ctrl.Ac.shape == (n, n) and ctrl.Bc.shape == (n, 3) and ctrl.Bu.shape == (n, 1)
    assert ctrl.Cc.shape == (1, n) and ctrl.Dc.shape == (1, 3)
    assert ctrl.Ts == pytest.approx(0.002)
    # the controller itself is stable (all eigenvalues inside the unit circle)
    assert np.max(np.abs(np.linalg.eigvals(ctrl.Ac))) < 1.0


@pytest.mark.parametrize("which", ["report", "default"])
def test_dlqr_poles_match_the_continuous_design(params, ctrl, which) -> None:
    A, B, _, _ = linear_model(params)
    if which == "report":
        c = controller_ss(params, Q=Q_REPORT, R=R_REPORT)
        Kc, _, _ = ct.lqr(A, B, np.diag(Q_REPORT), R_REPORT)
        # the report's K, printed to 4 decimals: within half the last digit (measured 3.4e-5
        # at most; docs/parameters.md "< 0.001 %")
        np.testing.assert_allclose(Kc, [[-73.4847, -43.6178, 133.2959, 28.7986]], rtol=0, atol=5e-5)
    else:
        c = ctrl
        Kc, _, _ = ct.lqr(A, B, np.diag(Q_DEFAULT), R_DEFAULT)
    sc = np.sort_complex(np.linalg.eigvals(A - B @ Kc))
    zd = np.linalg.eigvals(c.Ad - c.Bd @ c.K)
    sd = np.sort_complex(np.log(zd.astype(complex)) / c.Ts)
    # dlqr with Qd = Q Ts, Rd = R Ts matches the continuous poles to first order in Ts only:
    # measured 2.2e-6 (shipped design, poles to -7.4/s) and 1.3e-5 (the report's, poles
    # -9.1 +- 8.4j/s, further out so the Ts terms weigh more).  host/design/discrete.py says 2e-5
    np.testing.assert_allclose(sd, sc, rtol={"report": 2e-5, "default": 5e-6}[which])
    assert c.kr == pytest.approx(c.K[0, 0], rel=1e-9)  # x is an integrator: kr = K_x


def test_default_force_clamp_is_the_commanded_acceleration_limit(params, ctrl) -> None:
    # u_max accelerates the cart at A_CMD_DEFAULT from upright, with the pendulum free:
    # one tick of the linear plant from rest with u_max gives that acceleration
    A, B, _, _ = linear_model(params)
    assert ctrl.u_max == pytest.approx(force_clamp(params)) == pytest.approx(A_CMD_DEFAULT / B[1, 0])
    xdd = (A @ np.zeros(4) + B[:, 0] * ctrl.u_max)[1]
    assert xdd == pytest.approx(A_CMD_DEFAULT) and A_CMD_DEFAULT < params.a_max
    # below M + m: part of the force goes into swinging the pendulum
    assert ctrl.u_max < (params.M + params.m) * A_CMD_DEFAULT
    with pytest.raises(ValueError, match="a_cmd"):
        force_clamp(params, 0.0)


def test_matrix_form_equals_structured_form(params, ctrl) -> None:
    rng = np.random.default_rng(1)
    z = rng.normal(size=ctrl.n) * 0.1
    v = [0.05, -0.02, 0.2]
    xh = ctrl.estimate(z, v)
    u = -float((ctrl.K @ xh)[0]) + ctrl.kr * v[2]
    assert ctrl.output(z, v) == pytest.approx(u, rel=1e-9)
    # saturated input enters the buffer's end; the buffer shifts
    z2 = ctrl.step(z, v, 3.0)
    assert z2[-1] == 3.0
    np.testing.assert_allclose(z2[4:-1], z[5:])


def test_balances_from_tilt(params, ctrl) -> None:
    r = simulate_loop(params, ctrl, [0, 0, 0.1, 0], 5.0, quantise=True)
    assert np.max(np.abs(r["phi"])) < 0.3
    late = r["t"] > 2.5
    # settled after the report's 2.5 s: measured 1.13 mrad (one ADC count) and 0.85 mm
    assert np.max(np.abs(r["phi"][late])) <= 2 * PHI_COUNT
    assert np.max(np.abs(r["x"][late])) <= 2e-3
    assert np.max(np.abs(r["u"])) <= ctrl.u_max
    # the shipped design holds the report's 5 m/s^2 ...
    assert np.max(np.abs(r["xddot"])) <= 5.0
    # ... where the report's weights need far more from 0.1 rad (about 22 m/s^2 here)
    # (with an estimator for the sensors' noise, observer 1, as the report's observer follows the sensors)
    rep = controller_ss(params, Q=Q_REPORT, R=R_REPORT, u_max=force_limit(params), observer=1.0)
    r = simulate_loop(params, rep, [0, 0, 0.1, 0], 5.0, quantise=True)
    # measured 21.6 m/s^2; the late tilt 0.99 mrad
    assert np.max(np.abs(r["xddot"])) > 15.0 and np.max(np.abs(r["phi"][r["t"] > 2.5])) <= 2 * PHI_COUNT


def test_acceleration_constraint_is_feasible_with_softer_weights(params) -> None:
    soft = controller_ss(params, Q=(0.2, 0.5, 0.0, 0.0), R=1.0)
    r = simulate_loop(params, soft, [0, 0, 0.1, 0], 6.0, quantise=True)
    assert np.max(np.abs(r["phi"])) < 0.3
    assert np.max(np.abs(r["xddot"])) <= 5.0
    assert abs(r["phi"][-1]) <= PHI_COUNT  # measured 0.17 mrad at 6 s


def test_reference_step_is_tracked(params, ctrl) -> None:
    r = simulate_loop(params, ctrl, [0, 0, 0, 0], 5.0, x_ref=0.2, quantise=True)
    # measured 0.32 mm short at 5 s (2 encoder counts; the response is still creeping in)
    assert abs(r["x"][-1] - 0.2) <= 1e-3
    off = np.where(np.abs(r["x"] - 0.2) > 0.01)[0]
    assert r["t"][off[-1]] < 2.5  # the report's settling constraint
    assert np.max(np.abs(r["phi"])) < 0.3


def test_saturation_is_fed_back(params) -> None:
    # a clamp below the design's own (2.88 N) saturates the command and still recovers.  2.5 N,
    # not the 2.0 N this test used with the previous default: simulate_loop starts the estimator
    # at z = 0 (it does not see the tilt at first, unlike the firmware), and the shipped
    # estimator, which trusts the model (OBSERVER_DEFAULT 0.25), sees it late enough that 2.0 N
    # no longer catches it from there (docs/parameters.md)
    small = controller_ss(params, u_max=2.5)
    r = simulate_loop(params, small, [0, 0, 0.1, 0], 5.0)
    assert np.max(np.abs(r["u"])) == pytest.approx(2.5)
    assert abs(r["phi"][-1]) < 1e-4  # unquantised: measured 1.4e-6 rad at 5 s


def test_no_delay(params) -> None:
    c = controller_ss(params, delay=0.0)
    assert c.delay_steps == 0 and c.n == 4
    r = simulate_loop(params, c, [0, 0, 0.1, 0], 4.0)
    assert abs(r["phi"][-1]) < 1e-4  # unquantised: measured 7.6e-7 rad at 4 s


@pytest.mark.parametrize(
    "kwargs",
    [dict(design="nope"), dict(Q=(1, 2, 3)), dict(R=0.0), dict(design="gain"), dict(design="gain", K=(1, 1, 1, 1)),
     dict(rate=0), dict(delay=-1.0), dict(u_max=0.0), dict(K=(1, 2, 3, 4))],
)
def test_bad_arguments(params, kwargs) -> None:
    with pytest.raises(ValueError):
        controller_ss(params, **kwargs)


def test_zoh_matches_python_control(params) -> None:
    Ad, Bd, C, Ts = discretise(params)
    A, B, C0, D = linear_model(params)
    sd = ct.c2d(ct.ss(A, B, C0, D), Ts)
    np.testing.assert_allclose(Ad, sd.A, atol=1e-12)
    np.testing.assert_allclose(Bd, sd.B, atol=1e-12)


@pytest.mark.parametrize("design", ["lqr", "place"])
def test_separation_with_the_delay_as_states(params, design) -> None:
    from host.design.discrete import closed_loop_poles, delayed_plant

    c = controller_ss(params, design=design)
    A, B, C, Ts, d = delayed_plant(params)
    assert d == 5 and A.shape == (14, 14) and C.shape == (2, 14)
    ev = closed_loop_poles(params, c)
    assert np.max(np.abs(ev)) < 1.0
    # the exact predictor: feedback poles and filter poles, the rest pure delays (zeros,
    # numerically spread by the repeated root)
    want = np.concatenate([np.linalg.eigvals(c.Ad - c.Bd @ c.K), np.linalg.eigvals(c.Ad @ (np.eye(4) - c.M @ c.C))])
    big = ev[np.argsort(-np.abs(ev))[:8]]
    # measured 8e-13 (lqr) and 1.7e-10 (place): eigenvalue round-off of a 14x14 matrix
    np.testing.assert_allclose(np.sort_complex(big), np.sort_complex(want), atol=1e-8)
    # the 5-fold root at 0 spreads like (round-off)**(1/5): measured 0.022 / 0.027.  Kept at
    # 0.05 for that reason; a real pole there would be a slow mode near 1, not ~0.05
    assert np.all(np.abs(ev[np.argsort(-np.abs(ev))[8:]]) < 0.05)


def test_place_design_balances(params) -> None:
    c = controller_ss(params, design="place", u_max=force_limit(params))  # the report's drive, unclamped
    # the report's poles [-4.774 +- 5.9172j, -10.1, -10.2] mapped by exp(s Ts)
    s = np.sort_complex(np.log(np.linalg.eigvals(c.Ad - c.Bd @ c.K).astype(complex)) / c.Ts)
    np.testing.assert_allclose(s, np.sort_complex([-4.774 + 5.9172j, -4.774 - 5.9172j, -10.1, -10.2]), rtol=1e-9)  # measured 1e-11
    r = simulate_loop(params, c, [0, 0, 0.1, 0], 4.0, quantise=True)
    # measured peak 0.297 rad (the report's constraint is 0.3), final 0.04 mrad
    assert np.max(np.abs(r["phi"])) < 0.3 and abs(r["phi"][-1]) <= PHI_COUNT


def test_start_from_measurement(params, ctrl) -> None:
    z = ctrl.initial_state([0.05, 0.1, 0.0])
    assert z[0] == 0.05 and z[2] == 0.1 and not np.any(z[4:])
    with pytest.raises(ValueError):
        controller_ss(params, poles=[-1, -2, -3, -4])  # poles only with place
