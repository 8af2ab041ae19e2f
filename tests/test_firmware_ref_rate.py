"""The set-point ramp (issue 24): board parameter ``ref_rate_mm_s`` (robot file ``loop.ref_rate``).

While balancing, a new ``set_reference`` moves the controller's reference to the set-point at that
speed instead of at once -- the ramp ``Controller.schedule`` already runs for the catch mode's
hand-back, at the parameter's own rate.  Disarmed, or with the parameter at 0, the set-point is the
reference at once, as before.  One snippet on every interpreter (CPython, the unix port, the 32-bit
WebAssembly port, the emulated Pico); the closed loop it is for -- the step's acceleration on a cart
with gear play -- in lockstep HIL on the unix port and on the emulated Pico's pins.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import fwharness as H
from firmware import msgtable as T
from host.design.export import export
from sim.params import load_params

P = load_params()
RATE_MM_S = 500

RAMP = """
from firmware.app import App
from firmware import msgtable as T
hal = Hal()
app = App(hal, gains=G, config={'watchdog_ms': 0, 'arm_tilt_mrad': 500, 'stall_ms': 0})
c = app.ctrl
print('range', app.param_set(T.P_REF_RATE, 5001))
print('kept', app.params[T.P_REF_RATE])
print('set', app.param_set(T.P_REF_RATE, RATE))
# disarmed: the set-point is the reference at once
app.cmd_set_reference(100000)
print('disarmed_ramp', int(c.ramp))
print('disarmed_ref', app.ref)
app.cmd_set_reference(0)
app.step()
app.cmd_arm()
hal.adc = 2048
for k in range(5):
    app.step()
print('state', app.sup.state)
r0 = c.rr
app.cmd_set_reference(200000)
r = app.ref
print('r', r)
print('ramp', int(c.ramp))
print('st', c.rstep)
print('rr0', c.rr)
steps = array('i', [0] * 1000)
def ramp_ticks(nmax):
    n = 0
    while c.ramp and n < nmax:
        q = c.rr
        app.step()
        steps[n] = c.rr - q
        n += 1
    return n
n = ramp_ticks(1000)
print('ticks', n)
print('end', c.rr)
print('ramp_after', int(c.ramp))
ok = 1
for k in range(n - 1):
    if steps[k] != c.rstep:
        ok = 0
print('even', ok)
print('last', steps[n - 1])
# a new set-point mid-ramp: the ramp turns from where it has got to
app.cmd_set_reference(0)
for k in range(10):
    app.step()
mid = c.rr
app.cmd_set_reference(200000)
print('turn', int(c.rr == mid))
print('mid', mid)
n2 = ramp_ticks(1000)
print('ticks2', n2)
# the ramp's ticks allocate nothing
def more():
    app.cmd_set_reference(0)
    ramp_ticks(1000)
"""


def _code(interp: H.Interp) -> str:
    # the shipped design's table as App's gains module, the stand-in HAL, then the ramp's phases and
    # the allocation probe of this interpreter (none on the board: the ramp's ticks just run there)
    probe = (interp.alloc_run + "\nrun('alloc', more)\n") if interp.alloc_run else "more()\n"
    return (H.INTS_SRC + H.FAKE_HAL + H.gains_src("G", export(P)) + f"RATE = {RATE_MM_S}\n" + RAMP + probe)


def test_a_set_point_ramps_at_ref_rate_while_balancing(interp: H.Interp) -> None:
    res = H.parse_ints(interp.run(_code(interp), timeout=300))
    fd = export(P)
    assert res["range"] == T.R_OUT_OF_RANGE and res["kept"] == 0  # 5001 mm/s refused, the default kept
    assert res["set"] == T.OK
    assert res["disarmed_ramp"] == 0 and res["disarmed_ref"] > 0  # disarmed: at once
    assert res["state"] == 2  # balancing
    assert res["ramp"] == 1 and res["rr0"] == 0
    # the step per tick is the speed: 0.5 m/s x 2 ms in x LSB (rounded)
    want = RATE_MM_S * 1e-3 / P.rate / fd.lsb["x"]
    assert res["st"] == pytest.approx(want, abs=0.51)
    # evenly, every tick, to the set-point exactly: 0.2 m at 0.5 m/s, 0.4 s = 200 ticks at 500 Hz
    assert res["even"] == 1 and 0 < res["last"] <= res["st"]
    assert res["end"] == res["r"] and res["ramp_after"] == 0
    assert res["ticks"] == -(-res["r"] // res["st"])
    # 0.4 s at 500 Hz, within what rounding the step to whole x LSB changes (st within half an LSB)
    exact = 0.2 / (RATE_MM_S * 1e-3) * P.rate
    assert abs(res["ticks"] - exact) <= exact * 0.51 / want + 1, (res["ticks"], exact, want)
    # turned mid-ramp: from where it had got to, not from either set-point
    assert res["turn"] == 1 and 0 < res["mid"] < res["r"]
    assert res["ticks2"] == -(-(res["r"] - res["mid"]) // res["st"])
    if interp.alloc_run is not None:
        # the ramp's ticks under heap_lock on the unix port (0: no MemoryError), the bytes they
        # allocated on the WebAssembly port (0)
        assert res["alloc"] == 0, res


@pytest.mark.slow
def test_the_ramp_keeps_the_acceleration_limit_where_the_step_breaks_it() -> None:
    # the report's robot with 3 mm of gear play and 0.3 N of Coulomb friction, a table for it as
    # `upright commission` uploads it (gear_play, cart_coulomb): the 20 cm step in lockstep HIL on
    # the unix port, the true cart's acceleration, with the set-point at once and ramped
    from host.bench.robots import true_verdict
    from host.design.margin import candidates, fixed_design
    from host.operate.commission import compensation_counts, drive_params
    from host.operate.commission_lockstep import LockstepRobot
    from sim.scenario import load_scenario

    plant = P.replace(**{"motor.backlash": 0.003, "cart.coulomb": 0.3})
    cand = candidates(ki=(0.0,), a_cmd=(4.2,), names=("shipped",))[0]
    blob = fixed_design(plant, cand, deadband=compensation_counts(plant)).blob()
    sc = load_scenario("ref_step_20cm")
    out = {}
    with LockstepRobot(plant) as r:
        for rate in (0.0, RATE_MM_S * 1e-3):
            fw = plant.replace(**{"loop.ref_rate": rate})
            assert drive_params(fw)["ref_rate_mm_s"] == round(1000 * rate)
            r.upload(blob, fw)
            lg = r.run_scenario(sc)
            v = true_verdict(lg, sc, plant)
            assert not v["fell"]
            out[rate] = (v, lg)
    step, ramp = out[0.0][0], out[RATE_MM_S * 1e-3][0]
    assert step["peak_xddot"] > P.a_max  # the step breaks the limit on this cart
    assert ramp["peak_xddot"] <= 0.8 * P.a_max, (step, ramp)
    assert ramp["peak_phi"] < step["peak_phi"]
    # and the cart still gets there: within 2 cm of the set-point 1.5 s after the step
    lg = out[RATE_MM_S * 1e-3][1]
    t = np.asarray(lg["t"])
    x = np.asarray(lg["true_x"])
    assert abs(float(np.interp(2.0, t, x)) - 0.2) < 0.02


@pytest.mark.slow
def test_the_emulated_board_ramps_a_set_point_on_time(tmp_path) -> None:
    # the bundle's main.py on the emulated Pico, the play robot of the board tests (1 mm of play,
    # 0.2 N of Coulomb friction, gear_play and cart_coulomb set) on its pins, ref_rate_mm_s set over
    # the link: the ramp's ticks (schedule() every tick of it) run on time, no late tick, no overrun,
    # and the cart's acceleration is below the step's on the same board
    from host.boards.rp2040.board import build_bundle
    from host.hil.emulated import EmulatedHil
    from host.link import messages as M
    from sim.scenario import load_scenario

    plant, fw_set = H.play_robot()
    sc = dataclasses.replace(load_scenario("ref_step_20cm"), duration=2.5)
    peak = {}
    with EmulatedHil(build_bundle(tmp_path / "bundle")) as hil:
        for idx, v in fw_set.items():
            hil.request(M.BY_NAME["param_set"](index=idx, value=v))
        for rate in (0, RATE_MM_S):
            hil.request(M.BY_NAME["param_set"](index=T.P_REF_RATE, value=rate))
            run = hil.run(sc, plant)
            late = int(hil.request(M.ParamGet(index=T.STATUS_BASE + T.S_LATE)).value)
            assert int(hil.request(M.ParamGet(index=T.P_REF_RATE)).value) == rate
            assert not run.log["fw_faults"][60:].any()
            assert run.stats["nacks"] == [] and run.stats["telemetry_lost"] == 0
            assert late == 0 and run.stats["overruns"] == 0, (rate, late, run.stats["overruns"])
            peak[rate] = float(np.max(np.abs(run.log["xddot"])))
    assert peak[RATE_MM_S] < 0.7 * peak[0], peak


@pytest.mark.slow
def test_the_float_reference_ramps_as_the_firmware_does() -> None:
    # the report's robot, its 20 cm step with ref_rate_mm_s on the unix port (lockstep HIL, heap
    # locked) and the float design with the robot file's loop.ref_rate (sim.plantsim's loop): they
    # agree to the HIL tests' bound (two ADC counts, tests/test_hil_loop.py TOL_PHI), and both
    # differ from the step by far more -- the agreement is the ramp's, not a step's
    from host.hil.reference import float_reference
    from host.hil.session import HilSession
    from sim.scenario import load_scenario

    tol_phi = 2 * P.pot_range / 2**P.adc_bits
    sc = load_scenario("ref_step_20cm")
    ramped = P.replace(**{"loop.ref_rate": RATE_MM_S * 1e-3})
    with HilSession(heap_lock=True) as sess:
        run = sess.run_lockstep(sc, P, fw_params={"ref_rate_mm_s": RATE_MM_S})
    ref = float_reference(sc, ramped)
    step = float_reference(sc, P)
    assert np.all(run.log["fw_state"] == 2) and np.all(run.log["fw_faults"] == 0)
    err = float(np.max(np.abs(run.log["phi"] - ref["phi"])))
    assert err <= tol_phi, err
    assert float(np.max(np.abs(run.log["x"] - ref["x"]))) < 0.002
    assert float(np.max(np.abs(step["phi"] - ref["phi"]))) > 5 * tol_phi
    # the float loop's ramp: its peak acceleration well under the step's, its cart at the set-point
    assert float(np.max(np.abs(ref["xddot"]))) < 0.6 * float(np.max(np.abs(step["xddot"])))
    assert abs(float(ref["x"][int(5.0 * P.rate)]) - 0.2) < 0.005
