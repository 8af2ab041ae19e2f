"""Gear play in the firmware (issue 24): the board parameter ``gear_play`` (encoder counts, the robot
file's ``motor.backlash``) makes the estimator follow the wheel side of the play and gives the
predictor only the force the gear passes.

Without it, a cart whose encoder sits on the motor shaft takes the motor's free run across the
play for cart motion, the back-EMF compensation drives for a speed the cart does not have, and the
force at the flank's engagement breaks the report's acceleration limit (8.5 m/s^2 at 1.5 mm of
play on the report's robot, against 5).  CPython for the parts, the unix port in lockstep HIL for
the closed loop; the viper builds are compared with the plain code with the play on in
tests/test_firmware_fastpath.py, test_firmware_fasttick.py and, on the emulated RP2040,
test_rp2040_fast_equal.py.
"""

from __future__ import annotations

import pytest

import fwharness as H
from firmware import gains as G
from firmware import msgtable as T
from firmware.app import App
from firmware.controller import (CROSS_SHIFT, FC_COMP, LIM_FC, LIM_FCC, LIM_GAP, LIM_GH, LIM_GHB, LIM_HPX, LIM_KDU,
                                 LIM_KDV, Controller)
from firmware.sensors import Sensors
from firmware.store import MIGRATED, NAMES, ConfigStore, encode
from firmware.supervisor import BALANCING
from host.design.export import export
from sim import motor as smot
from sim import sensors as ssens
from sim.params import load_params

P = load_params()


def _controller(ghb: int) -> Controller:
    c = Controller(G.LAYOUT, G.FLAT)
    c.reset(0, 0)
    c.lim[4] = ghb
    return c


def _passed(gap: int, u: int, ghb: int) -> tuple[int, int]:
    # the rule: the motor side moves u through the play; the force beyond its flank passes
    v = gap + u
    if v > ghb:
        return v - ghb, ghb
    if v < -ghb:
        return v + ghb, -ghb
    return 0, v


def _raised(gap: int, u: int, ghb: int, hi: int, lo: int) -> int:
    # the crossing: toward a flank the motor side is off, u is raised to what reaches that flank,
    # at most the clamp >> CROSS_SHIFT
    if u > 0 and gap < ghb:
        return max(u, min(ghb - gap, hi >> CROSS_SHIFT))
    if u < 0 and gap > -ghb:
        return min(u, max(-ghb - gap, -((-lo) >> CROSS_SHIFT)))
    return u


def test_the_predictor_gets_only_the_force_the_gear_passes() -> None:
    ghb = 3000
    c = _controller(ghb)
    d = c.d
    assert d > 0
    kinds = {"free": 0, "flank": 0, "partial": 0, "raised": 0}
    for k in range(400):
        gap = c.lim[5]
        # a reference that jumps back and forth, far and near: the force reverses again and
        # again, strong and weak
        u = c.step(0, 0, (20000, -20000, 300, -300)[(k // 40) % 4])
        u0 = max(c.ulo, min(c.uhi, c.u_raw))  # the clamped command before the crossing
        assert u == _raised(gap, u0, ghb, c.uhi, c.ulo) == c.u, k
        ue, g = _passed(gap, u, ghb)
        assert (c.b[d - 1], c.lim[5]) == (ue, g), k
        kinds["free" if ue == 0 and u != 0 else ("flank" if ue == u else "partial")] += 1
        kinds["raised"] += u != u0
    assert all(kinds.values()), kinds  # crossed the play, pushed a flank, reached it mid-tick, raised


def test_a_small_force_crosses_the_play_at_a_quarter_of_the_clamp_and_lands_on_the_flank() -> None:
    # the motor side at the far flank, a force well under the crossing's: without the raise the
    # play takes 2 ghb / u ticks with no force on the cart; with it, ceil(2 ghb / (clamp >> 2))
    ghb = 1000
    c = _controller(ghb)
    c.lim[5] = -ghb
    h = c.uhi >> CROSS_SHIFT
    assert 0 < h < ghb  # the crossing takes more than one tick
    seen = []
    for _ in range(12):
        gap = c.lim[5]
        u = c.step(0, 0, -40)  # a reference 40 LSB ahead: a small positive force
        seen.append((gap, u, c.lim[5], c.b[c.d - 1]))
        if c.lim[5] == ghb and c.b[c.d - 1] != 0:
            break
    raised = [s for s in seen if s[2] < ghb or (s[0] < ghb and s[3] == 0)]
    assert all(0 < s[1] <= h for s in raised), seen  # never above a quarter of the clamp
    assert all(s[3] == 0 for s in raised), seen  # none of it reached the cart
    land = next(i for i, s in enumerate(seen) if s[2] == ghb)
    assert land + 1 == -(-2 * ghb // h), seen  # crossed at the raise, landed on the flank exactly
    assert seen[land][3] == 0 and seen[-1][3] > 0 and seen[-1][1] < h, seen  # then the force passes


def test_in_the_play_the_predictor_gets_the_coulomb_force_against_the_speed() -> None:
    # the motor side in the play passes nothing to the cart, whose dry friction (compensated by the
    # table only through the gear) brakes it: the predictor is given -fc sign(estimated speed); on a
    # flank the force the gear passes, as without friction
    ghb, fc = 100000, 300
    c = _controller(ghb)
    c.lim[LIM_FC] = fc
    d = c.d
    seen = set()
    for k in range(300):
        gap = c.lim[LIM_GAP]
        v = c.p[1]
        ym = 40 * k if k < 150 else 40 * (300 - k)  # the cart forward, then back
        u = c.step(ym, 0, (20000, -20000)[(k // 60) % 2])
        ue, g = _passed(gap, u, ghb)
        want = ue if ue != 0 else (-fc if v > 0 else (fc if v < 0 else 0))
        assert c.b[d - 1] == want and c.lim[LIM_GAP] == g, (k, gap, v, u, c.b[d - 1])
        if ue == 0:
            seen.add((v > 0) - (v < 0))
    assert seen >= {1, -1}, seen  # in the play both ways
    c.lim[LIM_GAP] = ghb  # on the forward flank: a push passes, no friction term
    u = c.step(0, 0, -20000)
    assert u > 0 and c.b[d - 1] == u


def test_in_the_play_the_coulomb_compensation_moves_the_motor_side_the_dutys_way() -> None:
    # the table's deadband compensation carries FC_COMP/32 of the cart's Coulomb friction in the
    # duty's direction; on a flank it cancels the friction, free in the play it drives the motor.
    # Braking a fast cart (force back, the back-EMF term forward: the duty forward) the motor side
    # crosses toward the back flank slower than the force alone says -- the gap model that left it
    # out reached the flank 10 ticks before the gear on a 3 mm commission-bench vertex, the
    # predictor braked a coasting cart, and the engagement's speed error made 10.9 m/s^2 (7.6 with it)
    ghb, fcc, kdu, kdv = 100000, 300, 1638, 18204
    for comp in (0, fcc):
        c = _controller(ghb)
        c.lim[LIM_FCC], c.lim[LIM_KDU], c.lim[LIM_KDV] = comp, kdu, kdv
        seen = []
        for k in range(40):
            gap, b_before = c.lim[LIM_GAP], c.b[c.d - 1]
            u = c.step(0, 0, -20000 if k < 20 else 20000)
            sv = kdu * u + kdv * c.vh
            s = 1 if sv > 0 or (sv == 0 and u > 0) else (-1 if sv < 0 or u < 0 else 0)
            w = u + comp * s
            assert c.lim[LIM_GAP] == max(-ghb, min(ghb, gap + w)), (comp, k, gap, u, c.vh)
            seen.append((gap, u, s))
        assert {s for _, _, s in seen} >= {1, -1}
    # and with the duty's sign the same, the gap moves by u + fcc; opposite, by u - fcc
    c = _controller(ghb)
    c.lim[LIM_FCC], c.lim[LIM_KDU], c.lim[LIM_KDV] = fcc, kdu, kdv
    c.p[1] = 2000  # a fast forward estimate and a reference behind: a braking force, the duty forward
    u = c.step(0, 0, 20000)
    assert u < 0 < kdu * u + kdv * c.vh and c.lim[LIM_GAP] == u + fcc, (u, c.vh, c.lim[LIM_GAP])
    # on a flank the force past it, less the compensation the friction takes, passes
    c = _controller(ghb)
    c.lim[LIM_FCC], c.lim[LIM_KDU], c.lim[LIM_KDV] = fcc, kdu, kdv
    c.lim[LIM_GAP] = ghb
    u = c.step(0, 0, -20000)
    assert u > 0 and c.lim[LIM_GAP] == ghb and c.b[c.d - 1] == u  # steady on the flank: u, as before


def test_the_coulomb_compensations_part_and_the_motors_constants_reach_the_gap_model() -> None:
    from host.operate.commission import COULOMB_COMP

    assert COULOMB_COMP == FC_COMP / 32  # the host's tables carry what the firmware counts on
    app = App(H.StandInHal(inc=2000), config={})
    assert app.param_set(T.P_CART_COULOMB, 50) == T.OK
    fc = app.ctrl.lim[LIM_FC]
    assert app.ctrl.lim[LIM_FCC] == (fc * FC_COMP) >> 5
    assert app.param_set(T.P_GEAR_PLAY, 20) == T.OK
    assert (app.ctrl.lim[LIM_KDU], app.ctrl.lim[LIM_KDV]) == (app.motor.kdu, app.motor.kdv)
    app.ctrl.reset(0, 0)  # arming keeps them
    assert app.ctrl.lim[LIM_FCC] == (fc * FC_COMP) >> 5 and app.ctrl.lim[LIM_KDU] == app.motor.kdu


def test_cart_coulomb_parameter_sets_the_predictors_force_and_survives_a_reset() -> None:
    app = App(H.StandInHal(inc=2000), config={})
    assert app.params[T.P_CART_COULOMB] == 0 and app.ctrl.lim[LIM_FC] == 0
    assert app.param_set(T.P_CART_COULOMB, 50) == T.OK
    fcu = app.ctrl.lim[LIM_FC]
    assert fcu > 0 and app._tel(fcu, 4) == 50  # 0.5 N in u LSB: telemetry's force reads it back
    assert app.param_set(T.P_CART_COULOMB, 1001) == T.R_OUT_OF_RANGE and app.ctrl.lim[LIM_FC] == fcu
    app.ctrl.reset(0, 0)  # arming resets the controller's state, not its parameters
    assert app.ctrl.lim[LIM_FC] == fcu
    assert T.P_CART_COULOMB in T.DRIVE_PARAMS  # refused while armed or balancing, like gear_play


def test_without_play_every_force_passes() -> None:
    c = _controller(0)
    for k in range(50):
        u = c.step(4000 if k < 25 else -4000, 0, 0)
        assert c.b[c.d - 1] == u and c.lim[5] == 0


def test_the_x_measurement_stands_for_the_wheel_side_of_the_play() -> None:
    # on a flank (the gap model at the measurement's time: d ticks back, the sensor delay the
    # predictor covers) the wheel is half the play behind the motor side the encoder reads; while
    # the motor side crosses, the encoder only bounds the wheel to within half the play of it, and
    # the estimator's own prediction is taken inside that window.  The reduced-order observer
    # (est 1) takes the measurement as its x, so the filter's x is the wheel side found.
    c = Controller(G.LAYOUT, G.FLAT)
    assert c.d > 0 and len(c.lim) == LIM_GH + c.d
    c.reset(0, 0)
    c.est = 1
    h, ghb = 400, 3000
    c.lim[LIM_GHB], c.lim[LIM_HPX] = ghb, h
    seen = []
    for k in range(80):
        gap_then = c.lim[LIM_GH]  # the gap model d ticks ago (oldest of its history)
        p0 = c.p[0]
        ym = 1000 + (40 * k if k < 40 else 3200 - 40 * k)  # the motor side, forward then back
        u = c.step(ym, 0, 0)
        seen.append((gap_then, p0, ym, u))
        if gap_then >= ghb:
            want = ym - h
        elif gap_then <= -ghb:
            want = ym + h
        else:
            want = min(max(p0, ym - h), ym + h)
        assert c.xf[0] == max(-c.lim[0], min(c.lim[0], want)), (k, seen[-1])
    gaps = [g for g, _, _, _ in seen]
    # both flanks and the crossing between them were exercised
    assert max(gaps) >= ghb and min(gaps) <= -ghb and any(-ghb < g < ghb for g in gaps), gaps
    c.reset(0, 0)
    assert all(c.lim[i] == 0 for i in range(LIM_GAP, len(c.lim)) if i != LIM_HPX) and c.lim[LIM_HPX] == h


def test_the_play_operator_follows_the_wheel_side() -> None:
    s = Sensors(G.FLAT, Controller(G.LAYOUT, G.FLAT).off)
    s.play = 5
    s.update(2048, 1000)
    assert s.yx == 0
    seen = []
    for enc in (1003, 1005, 1008, 1012, 1010, 1004, 1002, 995, 1000):
        s.update(2048, enc)
        seen.append((s.pos, s.wpos))
    # motor side (pos) vs wheel side (wpos): the wheel moves only once the motor side is 5 counts away
    assert seen == [(3, 0), (5, 0), (8, 3), (12, 7), (10, 7), (4, 7), (2, 7), (-5, 0), (0, 0)]
    assert s.yx == 0 << s.qx
    s.zero()
    assert s.wpos == 0 and s.yx == 0


def test_gear_play_parameter_derives_both_and_is_refused_while_balancing() -> None:
    app = App(H.StandInHal(inc=2000), config={})
    assert app.params[T.P_GEAR_PLAY] == 0 and app.ctrl.lim[4] == 0 and app.sensors.play == 0
    assert T.P_GEAR_PLAY in T.DRIVE_PARAMS
    assert app.param_set(T.P_GEAR_PLAY, 256) == T.R_OUT_OF_RANGE
    fd = export(P)
    ce = float(smot.back_emf_damping(P))
    for counts in (2, 10, 19, 60):
        assert app.param_set(T.P_GEAR_PLAY, counts) == T.OK
        # the controller finds the wheel side (half the play in x LSB); the sensors' play
        # operator stays off while there is a gap model
        assert app.sensors.play == 0
        assert app.ctrl.lim[LIM_HPX] == (counts << app.sensors.qx) >> 1
        # half the play in force x ticks: the motor side crosses it at the no-load speed u / ce
        half_m = 0.5 * counts / float(ssens.enc_counts_per_m(P))
        want = half_m * ce * float(P.rate) / fd.lsb["u"]
        assert app.ctrl.lim[4] == pytest.approx(want, rel=0.03)
    app.sup.state = BALANCING
    assert app.param_set(T.P_GEAR_PLAY, 5) == T.R_ARMED and app.params[T.P_GEAR_PLAY] == 60


def test_a_copy_saved_before_gear_play_loads_with_it_off(tmp_path) -> None:
    # a configuration an older firmware saved (13 parameters): kept, the new one at its default
    app = App(H.StandInHal(inc=2000), config={})
    old = list(app.params)[:T.P_GEAR_PLAY]
    old[T.P_POT_OFFSET] = 2100
    old[T.P_MOTOR_SIGN] = -1
    (tmp_path / NAMES[0]).write_bytes(bytes(encode(7, old, list(G.FLAT))))
    fresh = App(H.StandInHal(inc=2000), config={})
    fresh.sensors.play = 3  # whatever it had: the load sets it from the default
    st = fresh.attach_store(ConfigStore(str(tmp_path)))
    assert st == MIGRATED
    assert fresh.params[T.P_POT_OFFSET] == 2100 and fresh.params[T.P_MOTOR_SIGN] == -1
    assert fresh.params[T.P_GEAR_PLAY] == 0 and fresh.sensors.play == 0 and fresh.ctrl.lim[4] == 0
    assert not fresh.config_bad


@pytest.mark.slow
def test_gear_play_keeps_the_report_acceleration_limit_on_a_cart_with_play() -> None:
    # the report's robot with 1.5 mm of play, a table for it: the 20 cm step in lockstep HIL
    from host.bench.robots import true_verdict
    from host.design.margin import candidates, fixed_design
    from host.operate.commission import drive_params
    from host.operate.commission_lockstep import LockstepRobot
    from sim.scenario import load_scenario

    plant = P.replace(**{"motor.backlash": 0.0015})
    assert drive_params(plant) == {"gear_play": 10, "cart_coulomb": 0, "ref_rate_mm_s": 0}
    cand = candidates(ki=(0.0,), a_cmd=(4.2,), names=("shipped",))[0]
    blob = fixed_design(plant, cand).blob()
    sc = load_scenario("ref_step_20cm")
    peak = {}
    with LockstepRobot(plant) as r:
        for label, fw in (("without", P), ("with", plant)):
            r.upload(blob, fw)  # the robot file without play sets gear_play 0
            v = true_verdict(r.run_scenario(sc), sc, plant)
            assert not v["fell"]
            peak[label] = v["peak_xddot"]
    assert peak["without"] > P.a_max * 1.3  # the engagement's force: 8.5 m/s^2 when measured
    assert peak["with"] <= P.a_max


@pytest.mark.slow
def test_cart_coulomb_keeps_the_estimate_on_a_cart_that_friction_brakes_in_the_play() -> None:
    # the report's robot with the realistic set's roughest play and Coulomb friction (3 mm, 0.5 N), a
    # table for it: the 20 cm step in lockstep HIL with cart_coulomb 0 and with the robot file's
    from host.bench.robots import true_verdict
    from host.design.margin import candidates, fixed_design
    from host.operate.commission import compensation_counts, drive_params
    from host.operate.commission_lockstep import LockstepRobot
    from sim.scenario import load_scenario

    plant = P.replace(**{"motor.backlash": 0.003, "cart.coulomb": 0.5, "cart.stiction": 0.5})
    assert drive_params(plant) == {"gear_play": 19, "cart_coulomb": 50, "ref_rate_mm_s": 0}
    cand = candidates(ki=(0.0,), a_cmd=(4.2,), names=("shipped",))[0]
    blob = fixed_design(plant, cand, deadband=compensation_counts(plant)).blob()
    sc = load_scenario("ref_step_20cm")
    v = {}
    with LockstepRobot(plant) as r:
        r.upload(blob, plant)
        for fc in (0, 50):
            r.fw_set["cart_coulomb"] = fc
            v[fc] = true_verdict(r.run_scenario(sc), sc, plant)
            assert not v[fc]["fell"]
    assert v[50]["peak_xddot"] < 0.8 * v[0]["peak_xddot"], v
    assert v[50]["settle"] <= v[0]["settle"], v


@pytest.mark.slow
@pytest.mark.rp2040
def test_the_emulated_board_balances_a_cart_with_play_with_gear_play_on(tmp_path) -> None:
    # the bundle's main.py on the emulated Pico (HalPico, the paced loop with the heap locked,
    # the UART link), the plant with 1.5 mm of play and 0.2 N of Coulomb friction on its pins:
    # gear_play and cart_coulomb set over the link while
    # disarmed and read back, the step run (the wheel side and the gap model every tick: an allocation
    # would raise MemoryError under the locked heap and stop the robot), requests answered while
    # balancing, and the firmware's own clock saw no late tick
    import dataclasses

    from host.boards.rp2040.board import build_bundle
    from host.hil.emulated import EmulatedHil
    from host.link import messages as M
    from host.operate.commission import drive_params
    from sim.scenario import load_scenario

    plant = P.replace(**{"motor.backlash": 0.0015, "cart.coulomb": 0.2})
    counts = drive_params(plant)["gear_play"]
    fc = drive_params(plant)["cart_coulomb"]  # the predictor's Coulomb force in the play, too
    sc = dataclasses.replace(load_scenario("ref_step_20cm"), duration=3.0)
    with EmulatedHil(build_bundle(tmp_path / "bundle")) as hil:
        hil.request(M.BY_NAME["param_set"](index=T.P_GEAR_PLAY, value=counts))
        hil.request(M.BY_NAME["param_set"](index=T.P_CART_COULOMB, value=fc))
        assert int(hil.request(M.ParamGet(index=T.P_GEAR_PLAY)).value) == counts
        run = hil.run(sc, plant)
        late = int(hil.request(M.ParamGet(index=T.STATUS_BASE + T.S_LATE)).value)
        after = int(hil.request(M.ParamGet(index=T.P_GEAR_PLAY)).value)  # the run's table kept it
        after_fc = int(hil.request(M.ParamGet(index=T.P_CART_COULOMB)).value)
    assert counts == 10 and after == counts and fc == 20 and after_fc == fc
    # the state log holds the last HEARTBEAT's state (every heartbeat_ms = 100 ms, 50 ticks): one sent
    # just before the arm reads disarmed until the next, up to 50 ticks later plus the arm's own tick
    # (the heartbeat's phase moves with the set-up's requests: 50 ticks was one tick short when the
    # parameter table grew by ref_rate_mm_s); 60 ticks
    assert (run.log["fw_state"][60:] == BALANCING).all()
    assert not run.log["fw_faults"][60:].any()
    assert run.stats["nacks"] == [] and run.stats["telemetry_lost"] == 0
    assert late == 0 and run.stats["overruns"] == 0, (late, run.stats["overruns"])
    assert run.stats["tick_us_max"] < 1.5 * run.stats["period_us"], run.stats["tick_us_max"]
