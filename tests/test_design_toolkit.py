"""The design toolkit: a textbook cart-pole in the minimal robot-file form through ``upright design
--json`` with chosen weights and poles, every number checked against python-control computed
directly (one test per quantity); the robot file's forms and the Python API's objects.

The textbook robot is the University of Michigan "Control Tutorials for MATLAB" (CTMS) inverted
pendulum: M 0.5 kg, m 0.2 kg, b 0.1 N s/m, l 0.3 m to the centre of mass, I 0.006 kg m^2 about
it, g 9.8 -- with the same equations as the report (theta = pi + phi).  Its published state
space and LQR gain (Q = diag(5000, 0, 100, 0), R = 1: K = [-70.7107 -37.8345 105.5298 20.9238])
are checked too, an independent source.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path

import control as ct
import numpy as np
import pytest

from host.cli.main import main
from host.design import toolkit as tk
from host.design.discrete import closed_loop_poles, simulate_loop
from host.design.reduced import reduced_controller
from sim.params import ParamError, load_params

TEXTBOOK = """\
# CTMS inverted pendulum, minimal physical form
[cart]
M = 0.5
b = 0.1
[pendulum]
m = 0.2
L_cm = 0.3
I_cm = 0.006
[environment]
g = 9.8
"""
Q, R = [5000.0, 0.0, 100.0, 0.0], 1.0
POLES = [-2.0, -3.0, -4 + 1j, -4 - 1j]
OBS = [-20.0, -21.0, -22.0, -23.0]
RED = [-15.0, -16.0]
NOISE = [1.0, 1e-3, 2e-3]
PID = [80.0, 125.0, 8.0]
RATE, DELAY = 250.0, 0.008


def _cx(pairs: list[list[float]]) -> np.ndarray:
    return np.sort_complex(np.array([complex(a, b) for a, b in pairs]))


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("robot") / "textbook.toml"
    p.write_text(TEXTBOOK)
    return p


@pytest.fixture(scope="module")
def out(robot: Path) -> dict:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["design", "--params", str(robot), "--Q", ",".join(map(str, Q)), "--R", str(R),
                   "--poles", "-2,-3,-4+1j,-4-1j", "--observer-poles=-20,-21,-22,-23", "--noise", "1,1e-3,2e-3",
                   "--reduced-poles=-15,-16", "--pid", "80,125,8", "--rate", str(RATE), "--delay", str(DELAY),
                   "--json", "-"])
    assert rc == 0
    return json.loads(buf.getvalue())


@pytest.fixture(scope="module")
def ABCD(robot: Path) -> tuple[np.ndarray, ...]:
    # the textbook's formulas, written out (CTMS: p = I (M + m) + M m l^2)
    M, m, b, l, I, g = 0.5, 0.2, 0.1, 0.3, 0.006, 9.8
    p = I * (M + m) + M * m * l**2
    A = np.array([[0, 1, 0, 0], [0, -(I + m * l**2) * b / p, m**2 * g * l**2 / p, 0], [0, 0, 0, 1],
                  [0, -m * l * b / p, m * g * l * (M + m) / p, 0]])
    B = np.array([[0], [(I + m * l**2) / p], [0], [m * l / p]])
    C = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    return A, B, C, np.zeros((2, 1))


def test_conventions_are_stated(out: dict) -> None:
    c = out["conventions"]
    assert "[x, xdot, phi, phidot]" in c["state"] and "theta = pi + phi" in c["angle"]
    assert "u = -K x + Nbar r" in c["state_feedback"] and "F (N)" in c["input"]
    assert out["robot"]["missing_sections"] == ["loop", "motor", "sensors"]
    assert out["robot"]["I_pivot"] == pytest.approx(0.006 + 0.2 * 0.3**2)


def test_A_B_C_D(out: dict, ABCD: tuple[np.ndarray, ...], robot: Path) -> None:
    A, B, C, D = ABCD
    for key, want in zip("ABCD", ABCD):
        np.testing.assert_allclose(out["plant"][key], want, rtol=1e-12, atol=1e-12)
    # the CTMS page's printed matrices
    np.testing.assert_allclose(np.array(out["plant"]["A"])[[1, 1, 3, 3], [1, 2, 1, 2]],
                               [-0.1818, 2.6727, -0.4545, 31.1818], atol=5e-5)
    # and control.linearize of the nonlinear I/O system
    lin = ct.linearize(tk.plant_nonlinear(load_params(robot)), np.zeros(4), np.zeros(1))
    np.testing.assert_allclose(lin.A, A, atol=1e-6)
    np.testing.assert_allclose(lin.B, B, atol=1e-6)


def test_transfer_functions_poles_and_zeros(out: dict, ABCD: tuple[np.ndarray, ...]) -> None:
    A, B, C, D = ABCD
    G = ct.ss(A, B, C, D)
    for i, key in enumerate(("x", "phi")):
        tf = out["plant"]["tf"][key]
        ref = ct.ss2tf(G[i, 0])
        for s in (0.5j, 1 + 2j, 10j, -3 + 0.1j):
            assert np.polyval(tf["num"], s) / np.polyval(tf["den"], s) == pytest.approx(complex(ref(s)), rel=1e-9)
    # zeros, the textbook's: X/F ~ (I + m l^2) s^2 - m g l, Phi/F ~ m l s (one s cancelled: CTMS's P_pend)
    w = math.sqrt(0.2 * 9.8 * 0.3 / (0.006 + 0.2 * 0.3**2))
    np.testing.assert_allclose(_cx(out["plant"]["tf"]["x"]["zeros"]), [-w, w], atol=1e-9)
    np.testing.assert_allclose(_cx(out["plant"]["tf"]["phi"]["zeros"]), [0.0], atol=1e-9)
    q = (0.006 + 0.2 * 0.3**2) * (0.5 + 0.2) - (0.2 * 0.3) ** 2
    np.testing.assert_allclose(out["plant"]["tf"]["phi"]["num"], [0.2 * 0.3 / q, 0.0], rtol=1e-9)
    np.testing.assert_allclose(out["plant"]["tf"]["phi"]["den"],
                               [1, 0.1 * (0.006 + 0.2 * 0.09) / q, -(0.5 + 0.2) * 0.2 * 9.8 * 0.3 / q,
                                -0.1 * 0.2 * 9.8 * 0.3 / q], rtol=1e-9)
    np.testing.assert_allclose(_cx(out["plant"]["poles"]), np.sort_complex(np.linalg.eigvals(A)), atol=1e-9)
    assert out["plant"]["controllability"]["rank"] == 4 and out["plant"]["observability"]["rank"] == 4
    assert out["plant"]["controllability"]["det_Wr"] == pytest.approx(np.linalg.det(ct.ctrb(A, B)), rel=1e-9)


def test_K_lqr(out: dict, ABCD: tuple[np.ndarray, ...]) -> None:
    A, B, _, _ = ABCD
    K, _, E = ct.lqr(A, B, np.diag(Q), R)
    np.testing.assert_allclose(out["lqr"]["K"], np.ravel(K), rtol=1e-9)
    np.testing.assert_allclose(out["lqr"]["K"], [-70.7107, -37.8345, 105.5298, 20.9238], atol=1e-4)  # CTMS
    np.testing.assert_allclose(_cx(out["lqr"]["poles"]), np.sort_complex(E), atol=1e-8)


def test_K_place(out: dict, ABCD: tuple[np.ndarray, ...]) -> None:
    A, B, _, _ = ABCD
    K = np.ravel(ct.place(A, B, POLES))
    np.testing.assert_allclose(out["place"]["K"], K, rtol=1e-9)
    np.testing.assert_allclose(_cx(out["place"]["poles"]), np.sort_complex(POLES), atol=1e-8)


def test_Nbar(out: dict, ABCD: tuple[np.ndarray, ...]) -> None:
    A, B, _, _ = ABCD
    for name in ("lqr", "place"):
        K, nbar = np.array(out[name]["K"])[None, :], out[name]["Nbar"]
        cl = ct.ss(A - B @ K, B * nbar, [[1.0, 0, 0, 0]], 0)
        assert float(ct.dcgain(cl)) == pytest.approx(1.0, rel=1e-10)
    assert out["lqr"]["Nbar"] == pytest.approx(-70.7107, abs=1e-4)  # CTMS


def test_L_observer_and_kalman(out: dict, ABCD: tuple[np.ndarray, ...]) -> None:
    A, B, C, _ = ABCD
    np.testing.assert_allclose(out["observer"]["L"], ct.place(A.T, C.T, OBS).T, rtol=1e-8)
    L = np.array(out["observer"]["L"])  # two outputs: the gain is not unique, the poles are
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(A - L @ C).real), np.sort(OBS), atol=1e-8)
    L, _, _ = ct.lqe(A, B, C, np.array([[NOISE[0] ** 2]]), np.diag(np.square(NOISE[1:])))
    np.testing.assert_allclose(out["kalman"]["L"], L, rtol=1e-8)


def test_reduced_observer(out: dict, robot: Path) -> None:
    ro = out["reduced_observer"]
    np.testing.assert_allclose(_cx(ro["poles"]), np.sort_complex(RED), atol=1e-9)
    # the controller with it: separation, the poles are the state feedback's and the observer's
    cl = _cx(out["controllers"]["place + reduced_observer"]["closed_loop_poles"])
    np.testing.assert_allclose(cl, np.sort_complex(POLES + RED), atol=1e-6)
    # and it reconstructs the unmeasured states of the linear plant from x, phi, F
    p = load_params(robot)
    obs = tk.reduced(p, RED)
    G, O = tk.plant(p), obs.as_ss()
    t = np.linspace(0, 2, 2001)
    u = np.sin(3 * t)
    x0 = [0.01, 0.2, 0.05, -0.3]
    xs = ct.forced_response(G, t, u, X0=x0, return_x=True)
    est = ct.forced_response(O, t, np.vstack([xs.outputs, u]), X0=[0.0, 0.0])
    err = np.abs(np.asarray(est.outputs) - np.asarray(xs.states))
    # the open-loop plant diverges (10^4 by 2 s): the error is relative, the rest interpolation of the input
    assert err[:, 0].max() > 0.1 and err[:, -1].max() < 1e-5 * np.abs(np.asarray(xs.states)[:, -1]).max()


def test_discrete_matrices(out: dict, ABCD: tuple[np.ndarray, ...]) -> None:
    A, B, C, D = ABCD
    Ts = 1 / RATE
    ref = ct.c2d(ct.ss(A, B, C, D), Ts, method="zoh")
    ref2 = ct.sample_system(ct.ss(A, B, C, D), Ts)
    dd = out["discrete"]
    assert dd["Ts"] == Ts and dd["delay_steps"] == 2
    for key in "ABCD":
        np.testing.assert_allclose(dd["plant"][key], getattr(ref, key), rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(dd["plant"][key], getattr(ref2, key), rtol=1e-10, atol=1e-14)
    Kd, _, _ = ct.dlqr(ref.A, ref.B, np.diag(Q) * Ts, R * Ts)
    np.testing.assert_allclose(dd["lqr"]["K"], np.ravel(Kd), rtol=1e-8)
    np.testing.assert_allclose(dd["place"]["K"], np.ravel(ct.place(ref.A, ref.B, np.exp(np.array(POLES) * Ts))), rtol=1e-7)
    np.testing.assert_allclose(dd["observer"]["L"], ct.place(ref.A.T, ref.C.T, np.exp(np.array(OBS) * Ts)).T, rtol=1e-7)
    Lk, _, _ = ct.dlqe(ref.A, ref.B, ref.C, np.array([[NOISE[0] ** 2]]), np.diag(np.square(NOISE[1:])))
    np.testing.assert_allclose(dd["kalman"]["L"], Lk, rtol=1e-8)
    # the delay line: y[k] = C x[k-2]
    Ax = np.array(dd["delayed_plant"]["A"])
    assert Ax.shape == (8, 8) and np.allclose(np.array(dd["delayed_plant"]["C"])[:, 6:], np.eye(2))


def test_discrete_reduced_observer_with_the_delay(out: dict) -> None:
    dd = out["discrete"]
    Ts = 1 / RATE
    np.testing.assert_allclose(_cx(dd["reduced_observer"]["poles"]), np.sort_complex(np.exp(np.array(RED) * Ts)), atol=1e-9)
    sf = np.array(dd["lqr"]["poles"]).dot([1, 1j])
    for name, n, est in (("lqr + reduced_observer", 2, np.exp(np.array(RED) * Ts)),
                         ("lqr + observer", 4, np.exp(np.array(OBS) * Ts)),
                         ("lqr + kalman", 4, np.array(dd["kalman"]["poles"]).dot([1, 1j]))):
        c = dd["controllers"][name]
        assert np.array(c["Ac"]).shape == (n + 2, n + 2)  # the estimator's states + 2 stored inputs
        cl = _cx(c["closed_loop_poles"])
        big = np.sort_complex(cl[np.abs(cl) > 0.05])  # the delay line's poles sit (numerically spread) at 0
        np.testing.assert_allclose(big, np.sort_complex(np.concatenate([sf, est])), atol=1e-6, err_msg=name)


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")  # python-control's own margins code
def test_margins(out: dict, ABCD: tuple[np.ndarray, ...]) -> None:
    A, B, C, D = ABCD
    K = np.array(out["lqr"]["K"])[None, :]
    gm, pm, _, wg, wp, _ = ct.stability_margins(ct.ss(A, B, K, 0))
    m = out["controllers"]["lqr (state feedback)"]["margins"]
    assert m["gain_margin"] == pytest.approx(gm, rel=1e-6) and m["phase_margin_deg"] == pytest.approx(pm, rel=1e-6)
    assert m["w_gain_crossover"] == pytest.approx(wp, rel=1e-6) and m["w_phase_crossover"] == pytest.approx(wg, rel=1e-6)
    s = ct.tf("s")
    Cpid = PID[0] + PID[1] / s + PID[2] * s / (1 + s / 100.0)
    Pphi = ct.ss2tf(ct.ss(A, B, C, D)[1, 0])
    gm, pm, _, _, _, _ = ct.stability_margins(Pphi * Cpid)
    assert out["pid"]["margins"]["gain_margin"] == pytest.approx(gm, rel=1e-5)
    assert out["pid"]["margins"]["phase_margin_deg"] == pytest.approx(pm, rel=1e-5)
    # the observer-based loop, broken at the plant input
    L = np.array(out["observer"]["L"])
    Kc = ct.ss(A - B @ K - L @ C, L, -K, 0)
    gm, pm, _, _, _, _ = ct.stability_margins(-ct.series(ct.ss(A, B, C, D), Kc))
    mo = out["controllers"]["lqr + observer"]["margins"]
    assert mo["gain_margin"] == pytest.approx(gm, rel=1e-5) and mo["phase_margin_deg"] == pytest.approx(pm, rel=1e-5)


def test_text_output_and_json_file(robot: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "d.json"
    assert main(["design", "--params", str(robot), "--spec", "0.08,0.84", "--json", str(f)]) == 0
    text = capsys.readouterr().out
    assert "theta = pi + phi" in text and "PLACE: K =" in text and f"json: {f}" in text
    d = json.loads(f.read_text())
    assert d["place"]["spec"] == [0.08, 0.84] and "discrete" not in d  # no [loop], no --rate: continuous only
    assert np.abs(_cx(d["place"]["poles"]).imag).max() == pytest.approx(7.5999 * math.sqrt(1 - 0.62658**2), rel=1e-3)


@pytest.mark.parametrize("argv, needle", [
    (["--Q", "1,0,10", "--R", "0.01"], "--Q"),
    (["--Q", "1,0,10,0"], "--Q and --R"),
    (["--Q", "1,0,-1,0", "--R", "1"], "--Q"),
    (["--R", "0"], "--R"),
    (["--poles", "2,-3,-4,-5"], "--poles"),
    (["--poles", "-2,-3,-4+1j,-4-2j"], "conjugate"),
    (["--observer-poles=-1,-2"], "--observer-poles"),
    (["--reduced-poles=-1,x"], "--reduced-poles"),
    (["--noise", "1,0,1"], "--noise"),
    (["--spec", "1.5,1"], "--spec"),
    (["--rate", "nan"], "--rate"),
    (["--rate", "500", "--delay", "0.0033"], "--delay"),
    (["--delay", "0.01"], "--delay needs --rate"),
    (["--poles", "-1,-2,-3,-4", "--spec", "0.1,1"], "--spec"),
    (["--Q", "1,0,1,0", "--R", "1", "--robust"], "--robust"),
])
def test_bad_flags_are_named_in_one_line(robot: Path, capsys: pytest.CaptureFixture[str], argv: list[str],
                                         needle: str) -> None:
    try:
        rc = main(["design", "--params", str(robot), *argv])
    except SystemExit as exc:  # argparse's own checks
        rc = exc.code
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and needle in err, err


# ---------------------------------------------------------------- the robot file's forms
def _file(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "r.toml"
    p.write_text(text)
    return p


def test_I_pivot_is_converted_by_the_parallel_axis(tmp_path: Path, robot: Path) -> None:
    piv = load_params(_file(tmp_path, TEXTBOOK.replace("I_cm = 0.006", "I_pivot = 0.024")))
    ref = load_params(robot)
    assert piv.I_cm == pytest.approx(0.006, rel=1e-12) and piv.physical == pytest.approx(ref.physical)
    with pytest.raises(ParamError, match="pendulum.I_pivot.*m L_cm"):
        load_params(_file(tmp_path, TEXTBOOK.replace("I_cm = 0.006", "I_pivot = 0.01")))
    with pytest.raises(ParamError, match="pendulum.I_pivot"):
        load_params(_file(tmp_path, TEXTBOOK.replace("I_cm = 0.006", "I_cm = 0.006\nI_pivot = 0.024")))


def test_the_forms_do_not_mix_and_name_what_is_missing(tmp_path: Path) -> None:
    with pytest.raises(ParamError, match="pendulum.m_cam.*cannot be mixed"):
        load_params(_file(tmp_path, TEXTBOOK.replace("m = 0.2", "m = 0.2\nm_cam = 0.1")))
    with pytest.raises(ParamError, match="pendulum.I_cm: missing"):
        load_params(_file(tmp_path, TEXTBOOK.replace("I_cm = 0.006", "")))
    with pytest.raises(ParamError, match="pendulum.L_cm: missing"):
        load_params(_file(tmp_path, TEXTBOOK.replace("L_cm = 0.3", "")))
    with pytest.raises(ParamError, match="pendulum.m_cam: missing"):
        load_params(_file(tmp_path, TEXTBOOK.replace("m = 0.2", "")))


def test_a_missing_section_is_named_where_it_is_needed(robot: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = load_params(robot)
    with pytest.raises(ParamError, match=r"^motor: section \[motor\] is not in"):
        _ = p.kt
    with pytest.raises(ParamError, match=r"^loop: .*loop\.rate"):
        _ = p.values["loop.rate"]
    assert p.replace(M=0.6).M == 0.6 and "motor.kt" not in p.values and getattr(p, "no_such", None) is None
    assert main(["design", "--params", str(robot), "--no-figures"]) == 2  # the report mode scores against [loop]
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no [loop] section" in err and "--Q/--R" in err
    assert main(["export", "--params", str(robot)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "section [loop]" in err and err.startswith("upright export: bad parameter")


def test_the_old_key_loads_with_a_one_line_note(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = load_params(_file(tmp_path, TEXTBOOK.replace("I_cm", "I")))
    assert p.I_cm == 0.006
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "pendulum.I is read as pendulum.I_cm" in err
    # the report's robot (geometric form, eq. 2.10 used as I_cm) is unchanged, and quiet
    d = load_params()
    assert d.I == pytest.approx(0.0128110, rel=1e-4) and d.I_pivot == pytest.approx(d.I + d.m * d.L**2)
    assert capsys.readouterr().err == ""


def test_reduced_observer_balances_like_the_full_estimator() -> None:
    """The report's robot, its 500 Hz loop and 10 ms delay: the shipped state feedback with the
    reduced-order observer instead of the Kalman filter, float closed loop on the nonlinear plant
    from 0.1 rad: it meets the report's constraints, as the full estimator does."""
    from host.design.discrete import controller_ss

    p = load_params()
    full = controller_ss(p)
    red = reduced_controller(p, full.K[0], [-40, -41], u_max=full.u_max)
    assert red.n == 2 + full.delay_steps and full.n == 4 + full.delay_steps
    cl = closed_loop_poles(p, red)
    assert np.max(np.abs(cl)) < 1
    for c in (full, red):
        r = simulate_loop(p, c, [0, 0, 0.1, 0], 4.0, start_from_measurement=True)
        assert np.max(np.abs(r["phi"])) < p.phi_max and np.max(np.abs(r["xddot"])) <= p.a_max
        assert abs(r["phi"][-1]) < 1e-3 and abs(r["x"][-1]) < 1e-3
