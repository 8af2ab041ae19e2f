"""``upright commission`` (issue 24 items 3-5): the margin design, the stages on lockstep HIL, the CLI.

The end-to-end runs use the firmware under the MicroPython unix port in lockstep HIL with a
simulated robot (:class:`host.operate.commission_lockstep.LockstepRobot`): the emulated RP2040
runs at ~0.1-0.2x real time, too slow for a whole commissioning in ``make test``.  Corners:
the robot where the shipped table cannot hold the pendulum still (inertia x0.5, masses x1.2,
kt x0.9, 20 ms), the soft pendulum (inertia x0.7) and the realistic cart (Coulomb friction,
stiction, backlash, deadband, minimum duty, pot nonlinearity).
"""

from __future__ import annotations

import csv
import json
import math
import numpy as np
import pytest

from host.design import margin as Mg
from host.design.discrete import controller_ss
from sim.params import load_params


def test_integral_controller_without_gain_is_the_inner_controller() -> None:
    p = load_params()
    inner = controller_ss(p)
    ic = Mg.IntegralController(inner, 0.0)
    rng = np.random.default_rng(1)
    z, zi = np.zeros(inner.n), np.zeros(ic.n)
    for _ in range(50):
        v = rng.normal(0.0, [0.05, 0.02, 0.1])
        u, us, z = inner.tick(z, v)
        ui, usi, zi = ic.tick(zi, v)
        assert ui == pytest.approx(u, abs=1e-12) and usi == pytest.approx(us, abs=1e-12)
    assert np.allclose(zi[:-1], z)


def test_integral_state_is_the_firmwares_sum_of_reference_minus_estimate() -> None:
    p = load_params()
    inner = controller_ss(p)
    ki = 1.5
    ic = Mg.IntegralController(inner, ki)
    k = math.copysign(ki, inner.kr)  # the export's sign rule: the integral pushes as the reference gain
    z = np.zeros(ic.n)
    e = 0.0
    rng = np.random.default_rng(2)
    for _ in range(40):
        v = np.array([rng.normal(0, 0.01), rng.normal(0, 0.01), 0.2])
        u = ic.output(z, v)
        assert u == pytest.approx(inner.output(z[:-1], v) + k * e, abs=1e-12)
        e += inner.Ts * (v[2] - inner.estimate(z[:-1], v)[0])
        z = ic.step(z, v, ic.saturate(u))
        assert z[-1] == pytest.approx(e, abs=1e-12)
    # the exported table carries the same gain, with the reference gain's sign
    fd = Mg.fixed_design(p, Mg.MarginCandidate("t", (1.994, 0.0, 0.4917, 0.00182), 0.01, 0.25, 4.73, ki=ki))
    assert fd.ki == ki and fd.tables["KI"][0] != 0 and math.copysign(1, fd.tables["KI"][0]) == math.copysign(1, inner.kr)


def test_confidence_box_widens_the_intervals_and_keeps_the_estimate() -> None:
    p = load_params()
    res = {"estimates": {"I": p.I * 1.1, "mL": p.m * p.L, "kt": p.kt, "b": p.b},
           "ci": {"I": [p.I * 1.05, p.I * 1.15], "kt": [p.kt * 0.999, p.kt * 1.001], "delay": [0.008, 0.012]}}
    box = Mg.confidence_box(res, p, widen=2.0, floor=0.03, realism={})
    lo, hi = box.factors["inertia"]
    assert lo == pytest.approx(1.1 * (1 - 2 * 0.05 / 1.1)) and hi == pytest.approx(1.1 * (1 + 2 * 0.05 / 1.1))
    assert box.factors["motor_constant"] == pytest.approx((0.97, 1.03))  # the floor, not the noise interval
    assert box.delay == pytest.approx((0.008, 0.012)) and box.realism == {}


def _evaluation(cand, centre: float, corner: float):
    # an Evaluation of two points (the box's centre, one corner): the step's |xdd| ratio as given
    from host.design.robust import CONSTRAINTS, Evaluation

    lim = {"phi_max": 0.3, "a_max": 5.0, "settle": 2.5}
    met = {s: {c: np.array([0.5, 0.5]) * lim[c] for c in CONSTRAINTS} for s in ("step", "push")}
    met["step"]["a_max"] = np.array([centre, corner]) * 5.0
    return Evaluation(cand, [], met, {s: dict(lim) for s in met})


def test_margin_design_prefers_the_candidate_with_margin_at_the_identified_robot(monkeypatch) -> None:
    # the box's worst corner must not outvote the robot measured: a candidate 1 % under the limit at
    # the box's centre (the identified robot) loses to one with the margin there, whatever the corners
    # say (at the report's robot such a table made 5.05 m/s^2 on the robot, where the batch read 4.98)
    p = load_params()
    tight, easy = Mg.candidates(ki=(0.0,), a_cmd=(4.73,), names=("x2", "shipped"))
    ev = {tight.name: _evaluation(tight, 0.99, 1.1), easy.name: _evaluation(easy, 0.85, 1.5)}
    monkeypatch.setattr(Mg, "evaluate", lambda params, c, box, push=False, engine=None: ev[c.name])
    box = Mg.confidence_box({"estimates": {}, "ci": {}}, p, realism={})
    md = Mg.design_with_margin(p, box, [tight, easy], top=2)
    assert md.candidate.name == easy.name and md.worst_ratio == pytest.approx(1.5)
    assert Mg.nominal_ratio(ev[tight.name]) == pytest.approx(0.99)
    assert {t["name"]: t["nominal_ratio"] for t in md.tried} == pytest.approx({tight.name: 0.99, easy.name: 0.85})
    # with the margin at the centre for both, the box's worst ratio decides
    ev[tight.name] = _evaluation(tight, 0.8, 1.1)
    assert Mg.design_with_margin(p, box, [tight, easy], top=2).candidate.name == tight.name


def test_margin_design_ranks_first_by_the_pendulum_kept_on_the_realistic_plant(monkeypatch) -> None:
    # a robot with play and friction: its design model scores (in_model: every constraint met with
    # margin by the better one), the robot as given keeps or loses the pendulum: a candidate that loses
    # it at any point of the box comes after one that loses it at fewer, whatever its in-model score
    from host.design.uncertainty import in_model

    real = load_params("sim/plants/realistic_cart.toml")
    model = in_model(real)
    good, safe = Mg.candidates(ki=(0.0,), a_cmd=(4.73,), names=("x2", "shipped"))
    ev = {(False, good.name): _evaluation(good, 0.5, 0.6), (False, safe.name): _evaluation(safe, 0.8, 0.85),
          (True, good.name): _evaluation(good, 0.5, 5.0), (True, safe.name): _evaluation(safe, 0.5, 5.0)}
    ev[(True, good.name)].metrics["step"]["phi_max"] = np.array([0.5, 2.0]) * 0.3  # lost at the corner
    seen = []

    def evaluate(params, c, box, push=False, engine=None):
        realistic = params.values.get("motor.backlash", 0.0) != 0.0
        assert realistic or params.values == model.values  # the model or the robot as given, nothing else
        seen.append(realistic)
        return ev[(realistic, c.name)]

    monkeypatch.setattr(Mg, "evaluate", evaluate)
    box = Mg.confidence_box({"estimates": {}, "ci": {}}, model, realism={})
    md = Mg.design_with_margin(real, box, [good, safe], top=2)
    assert md.candidate.name == safe.name and [c.name for c in md.runners_up] == [good.name]
    assert {t["name"]: t["falls_realistic"] for t in md.tried} == {good.name: 1, safe.name: 0}
    assert any(seen) and not all(seen)  # scored in-model, the falls on the robot as given
    # a robot without realism is its own design model: the in-model score decides
    seen.clear()
    assert Mg.design_with_margin(model, box, [good, safe], top=2).candidate.name == good.name
    assert not any(seen)


def _cli(capsys, *args: str) -> tuple[int, str]:
    from host.cli.main import main

    rc = main(["commission", *args])
    return rc, capsys.readouterr().err


def test_cli_refuses_bad_options(tmp_path, capsys) -> None:
    rc, err = _cli(capsys, "--out", str(tmp_path))
    assert rc == 2 and "--port" in err
    rc, err = _cli(capsys, "--port", "/dev/null", "--plant", "soft_pendulum", "--out", str(tmp_path))
    assert rc == 2 and "--plant goes with --virtual" in err
    (tmp_path / "commission.json").write_text(json.dumps({"done": [], "data": {}}))
    rc, err = _cli(capsys, "--virtual", "--out", str(tmp_path))
    assert rc == 2 and "--resume" in err
    rc, err = _cli(capsys, "--virtual", "--resume", "--out", str(tmp_path / "nothing"))
    assert rc == 2 and "no commission.json" in err


def _hard_corner():
    from host.design.robust import plant_toml
    from host.design.uncertainty import Point

    p = load_params()
    pt = Point({"inertia": 0.5, "cart_mass": 1.2, "pendulum_mass": 1.2, "motor_constant": 0.9}, 10, True)
    return p, pt, plant_toml(pt, p)


def _commission(plant, out, params_in=None):
    from host.operate.commission import Commission
    from host.operate.commission_lockstep import LockstepRobot

    lines: list[str] = []
    with LockstepRobot(plant) as r:
        c = Commission(r, out, params_in=params_in, say=lines.append, fast=True)
        try:
            data = c.run()
            err = None
        except Exception as exc:  # noqa: BLE001 - returned for the test to judge
            data, err = c.state["data"], exc
        after = None
        if err is None:
            from host.bench.robots import true_verdict
            from sim.scenario import load_scenario

            after = [true_verdict(r.run_scenario(load_scenario(n)), load_scenario(n), plant)
                     for n in ("ref_step_20cm", "push_0p2N_5s")]
    return data, err, after, lines


@pytest.mark.slow
def test_commission_the_robot_the_shipped_table_cannot_hold(tmp_path) -> None:
    from host.bench.robots import true_verdict
    from host.operate.commission import weighed
    from host.operate.commission_lockstep import LockstepRobot
    from host.studies.identify import robot_toml
    from sim.scenario import load_scenario

    design, _, text = _hard_corner()
    (tmp_path / "plant.toml").write_text(text)
    plant = load_params(tmp_path / "plant.toml")
    sc = load_scenario("ref_step_20cm")
    with LockstepRobot(plant) as r:
        r.fw_params = design  # the shipped table
        shipped = true_verdict(r.run_scenario(sc), sc, plant)
    assert not shipped["pass"], shipped
    (tmp_path / "weighed.toml").write_text(robot_toml(weighed(design, plant)))
    data, err, after, lines = _commission(plant, tmp_path / "c", tmp_path / "weighed.toml")
    assert err is None, (err, lines)
    e = data["identify"]["estimates"]
    assert e["I"] == pytest.approx(plant.I, rel=0.1) and e["kt"] == pytest.approx(plant.kt, rel=0.05)
    assert e["delay"] == pytest.approx(plant.delay, abs=1.5 / plant.rate)
    assert all(v["pass"] for v in data["verify"].values()), data["verify"]  # from telemetry
    assert all(v["pass"] for v in after), after  # and in truth
    assert data["balance"]["tries"][0]["amplitude_n"] < data["balance"]["amplitude_n"]  # it grew
    html = (tmp_path / "c" / "report.html").read_text()
    assert html.count("data:image/png;base64") >= 3 and "margin" in html
    assert load_params(tmp_path / "c" / "robot.toml").I == pytest.approx(e["I"])


@pytest.mark.slow
def test_commission_the_soft_pendulum_and_resume(tmp_path) -> None:
    from host.operate.commission import STAGES, Commission
    from host.operate.commission_lockstep import LockstepRobot

    plant = load_params("sim/plants/soft_pendulum.toml")
    out = tmp_path / "c"
    with LockstepRobot(plant) as r:  # stop after the first design, as if the session ended
        Commission(r, out, say=lambda s: None, fast=True).run(STAGES[:5])
    st = json.loads((out / "commission.json").read_text())
    assert st["done"] == list(STAGES[:5])
    # the cart-only run's PRBS bits are the stage's CART_DIV ticks long on every robot (the lockstep
    # robot's own default is 4: at 8 ms bits a cart with gear play only crosses its play)
    from host.operate.commission import CART_DIV

    with (out / "cart.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    duty = np.array([float(q["duty"]) for q in rows])
    on = np.flatnonzero(np.array([float(q["excite"]) for q in rows]) != 0)
    flips = np.flatnonzero(np.diff(np.sign(duty[on[0]:on[-1] + 1])) != 0)
    assert len(flips) > 10 and np.all(np.diff(flips) % CART_DIV == 0), np.diff(flips)[:20]
    cart_mtime = (out / "cart.csv").stat().st_mtime_ns
    with LockstepRobot(plant) as r:
        c = Commission(r, out, say=lambda s: None, fast=True)
        c.load()
        data = c.run()  # a fresh firmware: the table in force is uploaded again first
    assert (out / "cart.csv").stat().st_mtime_ns == cart_mtime  # not redone
    assert json.loads((out / "commission.json").read_text())["done"] == list(STAGES)
    e = data["identify"]["estimates"]
    assert e["I"] == pytest.approx(plant.I, rel=0.05) and e["mL"] == pytest.approx(plant.m * plant.L, rel=0.05)
    assert all(v["pass"] for v in data["verify"].values()), data["verify"]


@pytest.mark.slow
def test_a_design_the_robot_fails_gives_way_to_the_runner_up(tmp_path) -> None:
    # the verification judges on the robot: the first choice is made one that settles the step far
    # too slowly (a fiftieth of the position weight), the design's own choice its runner-up
    from host.design.margin import candidates
    from host.design.robust import Candidate
    from host.operate.commission import STAGES, Commission
    from host.operate.commission_lockstep import LockstepRobot

    plant = load_params("sim/plants/soft_pendulum.toml")
    out = tmp_path / "c"
    with LockstepRobot(plant) as r:
        Commission(r, out, say=lambda s: None, fast=True).run(STAGES[:8])
    st = json.loads((out / "commission.json").read_text())
    good = st["data"]["design2"]
    pid = load_params(out / "robot_id.toml")
    s = candidates(ki=(0.0,), a_cmd=(good["a_cmd"],), names=("shipped",))[0]
    slow = type(s)("slow", (s.Q[0] / 50, *s.Q[1:]), s.R, s.observer, s.a_cmd, ki=0.0)
    st["data"]["design2"] = good | slow.as_dict(pid) | {"table_label": "final design slow",
                                                       "runners_up": [Candidate.from_dict(good).as_dict(pid)]}
    (out / "commission.json").write_text(json.dumps(st))
    lines: list[str] = []
    with LockstepRobot(plant) as r:
        c = Commission(r, out, say=lines.append, fast=True)
        c.load()
        data = c.run()
        tab = r.blob
    assert [t["name"] for t in data["verify_tries"]] == ["slow", good["name"]], (data["verify_tries"], lines)
    assert data["verify_tries"][0]["measured_ok"] is False and data["verify_tries"][1]["measured_ok"] is True
    assert all(v["pass"] for v in data["verify"].values()), data["verify"]
    assert data["design2"]["name"] == good["name"] and data["design2"]["chosen_by_model"] == "slow"
    assert tab == (out / "table.bin").read_bytes()  # the runner-up's table is the one in force and saved
    assert "runner-up" in (out / "report.html").read_text()


@pytest.mark.slow
def test_commission_a_realistic_cart_refuses_or_verifies(tmp_path) -> None:
    # the realistic cart (dry friction, backlash, deadband): the identification of
    # host.studies.identify (viscous model) is biased there; the commissioning must either
    # verify the robot or stop at a named stage in one line, its state resumable, never lose the pendulum
    from host.operate.commission import STAGES, CommissionError

    plant = load_params("sim/plants/realistic_cart.toml")
    data, err, after, lines = _commission(plant, tmp_path / "c")
    st = json.loads((tmp_path / "c" / "commission.json").read_text())
    assert not any(t["fell"] for t in data.get("balance", {}).get("tries", []))
    if "design1" in st["done"]:
        # the balancing run's table knows the play the cart-only run found (the firmware's gear_play)
        play = data["cart"]["estimates"].get("backlash", 0.0)
        assert play > 3e-4  # the 1 mm of this plant, found by the dry fit
        assert load_params(tmp_path / "c" / "robot_stage1.toml").values["motor.backlash"] == pytest.approx(play)
    if "design2" in st["done"]:
        # the final design's box is scored on the design model (in_model): with the robot file's 1 mm of
        # play and 0.2 N of Coulomb friction in the batch's plant and none of the firmware's
        # compensation in its controller, every run of the box hunts and every candidate scores 5.0
        from host.design.robust import UNSETTLED

        assert data["design2"]["worst_ratio"] < UNSETTLED, data["design2"]
    if err is None and not all(v.get("pass", True) for v in data["verify"].values()):
        # the commissioning ran to its end and its own verification says FAIL (the CLI exits 1 with
        # "verification FAIL"): a refusal at the last stage, in the robot's own telemetry. Seen at
        # integration: the step settles in 4.66 s by telemetry (truth: never inside the 2 % band, a
        # limit cycle) and |xdd| reads 2.6 m/s^2 where the truth peaks at 7.2 (backlash impacts the
        # motor's encoder does not see). The cart-only stage finds the 1 mm of play, so the
        # verification says it cannot judge the acceleration limit instead of passing it
        assert set(data["verify"]) == {"ref_step_20cm", "push_0p2N_5s"}, data["verify"]
        play = data["cart"]["estimates"].get("backlash", 0.0)
        if play > 3e-4:
            assert not any(v["xdd_measurable"] for v in data["verify"].values()), data["verify"]
            assert any("gear play" in ln for ln in lines), lines
    elif err is None:
        # verified from telemetry: then the truth passes too (never a PASS the plant contradicts)
        assert all(v["pass"] for v in after), after
    else:
        assert isinstance(err, CommissionError), err
        stage = str(err).split(":")[0]
        assert stage in STAGES and stage not in st["done"] and "\n" not in str(err)
        assert st["done"] == list(STAGES[:STAGES.index(stage)])


def test_the_design_model_is_the_robot_without_its_plant_realism() -> None:
    # what a commissioning's designs are scored on: the identified robot file with its Coulomb
    # friction, play, deadband, minimum duty and pot nonlinearity at 0, everything else as it was
    from host.design.uncertainty import REALISM, in_model

    p = load_params("sim/plants/realistic_cart.toml")
    q = in_model(p)
    assert any(p.values.get(k, 0.0) != 0.0 for k in REALISM.values())
    assert all(q.values.get(k, 0.0) == 0.0 for k in REALISM.values())
    assert {k: v for k, v in q.values.items() if k not in REALISM.values()} == \
        {k: v for k, v in p.values.items() if k not in REALISM.values()}
    assert in_model(q) is q  # already the model: unchanged


def test_the_lockstep_robot_says_when_the_board_refuses_the_excitation() -> None:
    # the firmware takes at most half the table's force clamp (OUT_OF_RANGE beyond): a refused EXCITE
    # is an error naming the reason, never a log of zero duty taken for a cart that does not move
    # (the commissioning's cart stage once grew its amplitude into refusals and reported a stuck cart)
    from host.operate.board import BoardError
    from host.operate.commission_lockstep import LockstepRobot

    p = load_params()
    with LockstepRobot(p) as r:
        r.fw_params = p  # the shipped table: its clamp's half is 1.4 N
        with pytest.raises(BoardError, match="refused EXCITE.*out_of_range"):
            r.excite(2, 2.0, seconds=0.5, coast_s=0.2)
        run = r.excite(2, 1.0, seconds=0.5, coast_s=0.2)
        assert 0 < max(abs(run.columns["duty"])) <= 420  # 1 N: about 410 duty counts on the report's drive


def test_bench_identification_errors_against_the_robots_truth() -> None:
    from host.bench.commission import id_errors

    plant = load_params("sim/plants/realistic_cart.toml")
    data = {"cart": {"estimates": {"kt": plant.kt * 0.9, "coulomb": 0.25, "backlash": math.nan}},
            "identify": {"estimates": {"I": plant.I * 1.05, "kt": plant.kt * 1.02, "b": plant.b}}}
    e = id_errors(data, plant)
    assert e["err_I"] == pytest.approx(0.05) and e["err_b"] == pytest.approx(0.0)
    assert e["err_kt"] == pytest.approx(0.02)  # the final identification's, not the cart stage's
    assert e["err_coulomb"] == pytest.approx(0.25 - plant.values["cart.coulomb"])  # absolute, N
    assert "err_backlash" not in e and "err_mL" not in e  # not estimated (nan) or not in the data
    assert id_errors({}, plant) == {}


def test_a_cart_with_gear_play_is_designed_with_the_lower_clamp() -> None:
    # the force clamp of both designs: the margin design's own, or PLAY_A_CMD for a play between
    # the verification's limit and PLAY_A_CMD_MAX (docs/parameters.md: the engagement's peak)
    from host.operate.commission import PLAY_A_CMD, PLAY_A_CMD_MAX, VERIFY_PLAY_MAX, play_a_cmd

    p = load_params()
    assert play_a_cmd(p) == Mg.A_CMD
    assert play_a_cmd(p.replace(**{"motor.backlash": 0.5 * VERIFY_PLAY_MAX})) == Mg.A_CMD
    assert play_a_cmd(p.replace(**{"motor.backlash": 1e-3})) == (PLAY_A_CMD,)
    assert play_a_cmd(p.replace(**{"motor.backlash": PLAY_A_CMD_MAX})) == (PLAY_A_CMD,)
    assert play_a_cmd(p.replace(**{"motor.backlash": 2 * PLAY_A_CMD_MAX})) == Mg.A_CMD
    assert PLAY_A_CMD < min(Mg.A_CMD)


def test_the_weighed_robot_file_has_the_robots_masses_and_measured_supply() -> None:
    # a cart-only log gives n gear V kt / (r R), not kt apart from the supply: the person measures it
    from host.operate.commission import weighed

    design = load_params()
    plant = design.replace(**{"cart.M": design.M * 1.2, "motor.V_supply": design.values["motor.V_supply"] * 0.85,
                              "motor.kt": design.kt * 1.1})
    w = weighed(design, plant)
    assert w.M == pytest.approx(plant.M) and w.values["motor.V_supply"] == pytest.approx(plant.values["motor.V_supply"])
    assert w.kt == pytest.approx(design.kt)  # what the cart-only run identifies stays the datasheet's


def test_the_verification_tries_one_of_each_weight_set_first() -> None:
    # the ki and clamp variants of one weight set fail together on a robot far more often than two
    # weight sets do: fallback_order interleaves the sets, keeping the design's order within a round
    from host.operate.commission import FAST_WEIGHTS, VERIFY_FALLBACKS, fallback_order

    by = {c.name: c for c in Mg.candidates(ki=(0.0, 1.0), a_cmd=(4.2, 4.73))}
    names = ["shipped_a4.2_ki1", "shipped_a4.73_ki0", "x2_a4.2_ki0", "shipped_a4.2_ki0", "x4_a4.2_ki1",
             "x2_a4.2_ki1", "x4_a4.2_ki0"]
    got = [c.name for c in fallback_order(by["shipped_a4.2_ki0"], [by[n] for n in names])]
    assert got == ["x2_a4.2_ki0", "x4_a4.2_ki1", "shipped_a4.2_ki1", "x2_a4.2_ki1", "x4_a4.2_ki0",
                   "shipped_a4.73_ki0", "shipped_a4.2_ki0"]
    assert sorted(got) == sorted(names)  # a reordering: nothing lost, nothing added
    assert fallback_order(by["x2_a4.2_ki0"], []) == []
    # x2 with a faster estimator is a weight set of its own
    two = [by[n] for n in ("x2_obs_fast_a4.2_ki0", "x2_obs_fast_a4.2_ki1", "x2_a4.2_ki0")]
    assert [c.name for c in fallback_order(by["shipped_a4.2_ki0"], two)] == [
        "x2_obs_fast_a4.2_ki0", "x2_a4.2_ki0", "x2_obs_fast_a4.2_ki1"]
    assert "x4" in FAST_WEIGHTS and VERIFY_FALLBACKS >= len(FAST_WEIGHTS)


def test_the_benchs_true_tables_pass_the_report_robot_with_the_first() -> None:
    # make bench section commission's reference: tables for the true parameters, by the commissioning's
    # rules; on the report's own robot the first candidate (the shipped weights) meets every constraint
    from host.bench.commission import true_tables
    from host.operate.commission_lockstep import LockstepRobot
    from sim.scenario import load_scenario

    p = load_params()
    scen = [load_scenario("ref_step_20cm"), load_scenario("push_0p2N_5s")]
    with LockstepRobot(p) as r:
        c = true_tables(r, p, scen)
    assert c["truth_pass"] and c["truth_fails"] == "" and c["truth_table"].startswith("shipped")
    assert 0.0 < c["truth_settle"] <= p.t_settle
