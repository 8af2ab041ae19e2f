"""The reduced-order observer in the firmware (issue 27 item 3): the gain table's ``EST`` field,
the fixed-point export and the firmware step against the float design.

The table of a :class:`host.design.reduced.ReducedOrderController` carries the observer in the
firmware's predictor-corrector form (``host.design.export.filter_gain``: ``M = Sy + Sw Lr``) and
``EST = 1``, with which the firmware takes x and phi straight from the sensors.  Checked here:
that form is the Gopinath observer exactly (poles, outputs), the firmware agrees with the float
controller within the bounds of ``tests/test_firmware_fixed_vs_float.py`` (same reasons, same
figures) under CPython, the MicroPython unix port and the 32-bit WebAssembly port, bit for bit
between them, the skipped rows change nothing but the cost, and an uploaded table with an
unknown estimator is refused.  Wall time about 15 s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from firmware import msgtable as T
from firmware.controller import Controller
import fwharness as H
from host.boards.mpyrun import wasm_available
from host.design.discrete import DiscreteController, closed_loop_poles, controller_ss, force_clamp, simulate_loop
from host.design.export import EST_FULL, EST_REDUCED, SMALL_MAX, VERSION, export, filter_gain
from host.design.reduced import REDUCED_POLES_DEFAULT, reduced_for
from sim.params import load_params

P = load_params()
FULL = controller_ss(P)
RED = reduced_for(P, FULL)
FD = export(P, RED)

# the bounds of tests/test_firmware_fixed_vs_float.py, for the same reasons (the force row's gains
# quantised at shift 10, the states in their formats).  Measured when set (reduced table, these four
# scenarios): force 0.024-0.027 N (12-14 LSB), speed estimate 2.0-2.5 LSB, closed-loop phi
# 0.0003-0.0006 rad -- as close as the full estimator's (0.026-0.033 N, 4.2 LSB, 0.0009-0.0016 rad)
U_TOL = 0.015 * force_clamp(P)
PHI_TOL = 2 * P.pot_range / 2**P.adc_bits
V_TOL = 6 * FD.lsb["xdot"]

SCENARIOS = H.REPORT_SCENARIOS


@pytest.fixture(scope="module")
def sequences():
    return {name: H.measurements(P, FD, **kw) for name, kw in SCENARIOS.items()}


def _as_full_form(ctrl) -> DiscreteController:
    # the reduced controller written as the firmware runs it, checked against controller_ss's own
    # equations (design="gain" with the same K) with the Kalman gain replaced by filter_gain's M
    M, est = filter_gain(ctrl)
    assert est == EST_REDUCED
    ff = ctrl.firmware_form()
    c = controller_ss(P, design="gain", K=ctrl.K[0], u_max=ctrl.u_max)
    I_MC = np.eye(4) - M @ c.C
    assert np.allclose(ff.Ac[:4, :4], c.Ad @ I_MC) and np.allclose(ff.Bc[:4, :2], c.Ad @ M)
    assert np.allclose(ff.Cc[0, :4], -(c.Kf @ I_MC)[0]) and np.allclose(ff.Dc[0, :2], -(c.Kf @ M)[0])
    assert np.allclose(ff.Ac[:4, 4:], c.Ac[:4, 4:]) and np.allclose(ff.Cc[0, 4:], c.Cc[0, 4:])
    assert np.array_equal(filter_gain(ff)[0], M) and filter_gain(ff)[1] == EST_REDUCED
    assert export(P, ff).flat() == FD.flat()  # the same table either way
    return ff


def test_table_says_which_estimator_and_the_shipped_one_is_full() -> None:
    from firmware import gains as G

    off = Controller(G.LAYOUT, G.FLAT).off
    assert G.VERSION == VERSION and G.FLAT[off["EST"]] == EST_FULL
    assert FD.tables["EST"] == [EST_REDUCED] and export(P).tables["EST"] == [EST_FULL]
    # the rows of the measured states are the identity, exactly: gain 2**S on their own channel
    m, sm = FD.tables["M"], FD.tables["SM"]
    assert (m[0], m[1]) == (1 << sm[0], 0) and (m[4], m[5]) == (0, 1 << sm[2])
    assert all(r.worst <= SMALL_MAX for r in FD.rows)  # the headroom proof holds for it too
    c = Controller(H.layout_of(FD), FD.flat())
    assert c.est == 1 and c.validate(FD.flat(), len(FD.flat()), VERSION) == T.OK


def test_the_firmware_form_is_the_gopinath_observer() -> None:
    # same closed-loop poles: Ad - Bd K, the observer's F at exp(s Ts), zeros for the delay line (a
    # nilpotent block of order ~10: its computed eigenvalues scatter around 0 by up to 0.03)
    ff = _as_full_form(RED)
    a = np.sort_complex(np.round(closed_loop_poles(P, RED), 9))
    b = np.sort_complex(np.round(closed_loop_poles(P, ff), 9))
    nz = lambda v: np.sort_complex(v[np.abs(v) > 0.5])  # noqa: E731
    assert np.allclose(nz(a), nz(b), atol=1e-7)
    want = np.exp(np.array(REDUCED_POLES_DEFAULT) * RED.Ts)
    assert len(nz(b)) == 6  # the four of Ad - Bd K and the observer's two
    for p in want:
        assert np.min(np.abs(nz(b) - p)) < 1e-9
    # and the same forces on the nonlinear loop, tick for tick (float, quantised sensors)
    r1 = simulate_loop(P, RED, [0, 0, 0.1, 0], 2.0, quantise=True, start_from_measurement=True)
    r2 = simulate_loop(P, ff, [0, 0, 0.1, 0], 2.0, quantise=True, start_from_measurement=True)
    assert np.max(np.abs(r1["u"] - r2["u"])) < 1e-9


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_command_within_twenty_force_lsb_of_float(sequences, name) -> None:
    H.check_force_against_float(FD, sequences[name], U_TOL, name)  # measured 0.024-0.027 N


def test_speed_estimate_matches_the_float_prediction(sequences) -> None:
    s = sequences["ref_step_0.2"]
    _, v = H.py_controller_run(FD, s.yx, s.yp, s.r)
    z = RED.initial_state()
    vf = []
    for k in range(len(s.yx)):
        vin = [s.yx[k] * FD.lsb["x"], s.yp[k] * FD.lsb["phi"], s.r[k] * FD.lsb["x"]]
        vf.append(RED.estimate(z, vin)[1])
        _, _, z = RED.tick(z, vin)
    err = np.max(np.abs(np.array(v) * FD.lsb["xdot"] - np.array(vf)))
    assert err <= V_TOL, f"{err:.5f} m/s"  # measured 2.0 LSB


@pytest.mark.parametrize("name", ["tilt_0.1", "ref_step_0.2", "push_0.2N"])
def test_closed_loops_agree_in_phi(name) -> None:
    H.check_closed_loops_agree(P, RED, FD, SCENARIOS[name], PHI_TOL, name)  # measured 0.0004-0.0006 rad


def test_skipping_the_identity_rows_changes_nothing(sequences) -> None:
    # EST 1 skips the filter rows of x and phi; the same table run through them (EST forced to 0)
    # gives the same numbers bit for bit, so the skip is pure saving
    s = sequences["tilt_0.1"]
    c1 = Controller(H.layout_of(FD), FD.flat())
    c0 = Controller(H.layout_of(FD), FD.flat())
    c0.est = 0
    for k in range(len(s.yx)):
        assert c1.step(s.yx[k], s.yp[k], s.r[k]) == c0.step(s.yx[k], s.yp[k], s.r[k])
        assert list(c1.p) == list(c0.p) and c1.vh == c0.vh
    assert list(c1.rf) == list(c0.rf)


def test_native_and_viper_steps_equal_bytecode(sequences) -> None:
    # the generated fast path (firmware/fastpath.py) takes the same branch under the unix port
    s = sequences["ref_step_0.2"]
    n = 600
    code = (H.flat_src(FD) + H.ints_src(YX=s.yx[:n], YP=s.yp[:n], R=s.r[:n]) + """
from firmware.controller import Controller
from firmware.fastpath import step_native, step_viper
cs = [Controller(LAYOUT, FLAT) for _ in range(3)]
bad = 0
for k in range(len(YX)):
    a = cs[0].step(YX[k], YP[k], R[k])
    b = step_native(cs[1], YX[k], YP[k], R[k])
    c = step_viper(cs[2], YX[k], YP[k], R[k])
    if a != b or a != c or list(cs[0].p) != list(cs[2].p):
        bad += 1
print(cs[0].est, bad)
""")
    from host.boards.mpyrun import run_unix

    assert run_unix(code).split() == ["1", "0"]


@pytest.mark.wasm
@pytest.mark.skipif(not wasm_available(), reason="node / MicroPython WebAssembly port not installed")
def test_32bit_port_gives_the_same_numbers(sequences) -> None:
    H.check_wasm_equals_cpython(FD, sequences["tilt_0.1"], n=1000)


def test_unknown_estimator_is_refused() -> None:
    c = Controller(H.layout_of(FD), FD.flat())
    o = c.off["EST"]
    for bad in (2, -1):
        t = list(FD.flat())
        t[o] = bad
        assert c.validate(t, len(t), VERSION) == T.R_BAD_SHAPE
    t = list(FD.flat())
    t[c.off["HDR"]] = VERSION - 1  # a table of the layout before EST
    assert c.validate(t, len(t), VERSION) == T.R_BAD_SHAPE


def test_cli_export_reduced(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from host.cli.main import main

    out = tmp_path / "g.py"
    assert main(["export", "--estimator", "reduced", "--out", str(out)]) == 0
    text = out.read_text()
    assert "estimator=reduced-order observer" in text and "continuous poles -5, -4 rad/s" in text
    ns: dict = {}
    exec(compile(text, str(out), "exec"), ns)
    assert list(ns["FLAT"]) == FD.flat()
    capsys.readouterr()
    for argv, word in ((["--reduced-poles=-5,-6"], "--estimator reduced"),
                       (["--estimator", "reduced", "--reduced-poles=1,-6"], "--reduced-poles"),
                       (["--estimator", "reduced", "--observer", "2"], "--observer")):
        try:
            rc = main(["export", *argv])
        except SystemExit as exc:  # argparse's own refusals
            rc = exc.code
        err = capsys.readouterr().err
        assert rc == 2 and word in err and len(err.strip().splitlines()) == 1, err
