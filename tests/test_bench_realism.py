"""``make bench`` section ``realism`` (host/bench/realism.py): what fails where, one effect at a time.

The section runs the firmware (unix port) in lockstep HIL; here one robot (the nominal), one
effect at two levels: about 10 s.
"""

from __future__ import annotations

import math

import pytest

from host.bench.realism import EFFECTS, study, summary
from host.bench.robots import failing_check
from host.design.uncertainty import REALISM
from sim.params import load_params


def test_the_first_failing_check_follows_the_report_constraints() -> None:
    p = load_params()
    ok = {"fell": False, "peak_phi": 0.1, "peak_xddot": 4.0, "settle": 1.0}
    assert failing_check(ok, p) == ""
    assert failing_check(ok | {"settle": math.inf}, p) == "settle"
    assert failing_check(ok | {"settle": p.t_settle + 0.01}, p) == "settle"
    assert failing_check(ok | {"peak_xddot": p.a_max + 0.01, "settle": math.inf}, p) == "xdd"
    assert failing_check(ok | {"peak_phi": p.phi_max}, p) == "phi"
    assert failing_check(ok | {"fell": True, "peak_phi": 1.5}, p) == "fell"


def test_every_effect_names_realism_keys() -> None:
    assert set(EFFECTS["all"]) == set(REALISM)
    assert all(set(keys) <= set(REALISM) for keys in EFFECTS.values())


def test_the_study_changes_one_thing_and_says_what_fails() -> None:
    rows = study(1, effects=("stiction",), levels=(0.1, 1.0))
    assert [(r["effect"], r["level"]) for r in rows] == [("ideal", 0.0), ("stiction", 0.1), ("stiction", 1.0)]
    ideal = rows[0]
    # the nominal robot with a table designed for it passes on the ideal plant: the baseline the rows change
    assert ideal["pass"] and ideal["fails"] == "", ideal
    assert rows[1]["value"] == "stiction=0.075" and rows[2]["value"] == "stiction=0.75"
    for r in rows:
        assert r["pass"] == (r["fails"] == ""), r  # a failing row names the constraint it fails
        assert r["table"] == ideal["table"]  # the same table throughout the robot's rows
    notes = summary(rows)
    assert notes[0].startswith("1 robots") and "ideal plant: 1/1 pass" in notes[0]
    assert notes[1].startswith("stiction: pass 10 % ")


@pytest.mark.parametrize("bad", [0, -1])
def test_no_robot_no_rows(bad: int) -> None:
    assert study(bad, effects=("stiction",), levels=(0.1,)) == []


def test_the_uploaded_table_compensates_most_of_the_coulomb_friction() -> None:
    from host.operate.commission import CART_DB_MAX, COULOMB_COMP, compensation_counts, deadband_counts
    from sim.motor import DUTY_MAX, duty_from_force

    p = load_params().replace(**{"motor.deadband": 0.01})
    assert compensation_counts(p) == deadband_counts(p) == round(0.01 * DUTY_MAX)  # no friction: the deadband
    pc = p.replace(**{"cart.coulomb": 0.3})
    want = deadband_counts(pc) + round(abs(float(duty_from_force(COULOMB_COMP * 0.3, 0.0, pc))))
    assert compensation_counts(pc) == want > deadband_counts(pc)
    assert compensation_counts(pc, 0.0) == deadband_counts(pc)  # the cart-only run's table: the deadband only
    assert compensation_counts(pc.replace(**{"cart.coulomb": 50.0})) == round(CART_DB_MAX * DUTY_MAX)  # capped


def test_coulomb_compensation_shortens_the_settling_of_a_dry_cart() -> None:
    # the nominal robot with 0.25 N of Coulomb friction, the firmware in lockstep HIL: without
    # compensation the step hunts (stick-slip, settling ~4.7 s); with the table's it settles
    from host.bench.robots import robots, true_verdicts
    from host.design.uncertainty import in_model
    from host.design.margin import candidates, fixed_design
    from host.operate.commission import compensation_counts
    from host.operate.commission_lockstep import LockstepRobot
    from sim.scenario import load_scenario

    plant = in_model(robots(1)[0][1]).replace(**{"cart.coulomb": 0.25})
    cand = candidates(ki=(0.0,), a_cmd=(4.2,), names=("shipped",))[0]
    step = [load_scenario("ref_step_20cm")]
    settle = {}
    with LockstepRobot(plant) as r:
        for a in (0.0, 0.8):
            r.upload(fixed_design(plant, cand, deadband=compensation_counts(plant, a)).blob(), plant)
            settle[a] = true_verdicts(r, plant, step)[0]["settle"]
    assert settle[0.0] > plant.t_settle, settle
    assert settle[0.8] < 0.6 * settle[0.0], settle
