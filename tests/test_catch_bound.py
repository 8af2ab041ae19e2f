"""The largest tilt any controller can right on this robot (issue 15 item 3; host/design/catch.py).

:func:`host.design.catch.drive_bound` computes it on the nonlinear plant with the true drive
(supply, back-EMF), ``|xddot| <= a_max`` and the track; these tests check that it

* lies below ``atan(a_max/g)`` and that both the track and the drive's speed bind (each
  dropped, it rises; both dropped, it is ``atan(a_max/g)``);
* rises when the drive's speed limit is removed with a 100x supply;
* is consistent with the firmware: a firmware run just above it does not recover, the
  firmware's best (0.33 rad) lies below it;
* is tight: its maneuver from just below it, replayed on :func:`sim.plant.simulate` with
  :func:`sim.motor.force_limits` (code independent of the bound's own integrator), rights the
  pendulum within every limit;
* is not beaten by a free acceleration profile (:func:`host.design.catch.direct_search`).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from host.bench.catch import run_tilt
from host.design.catch import DriveBound, direct_search, drive_bound, max_effort, physical_bound
from sim.motor import force_limits, no_load_speed
from sim.params import load_params
from sim.plant import dynamics, simulate

P = load_params()


@pytest.fixture(scope="module")
def bound() -> DriveBound:
    return drive_bound(P)


@pytest.mark.slow
def test_bound_lies_below_atan_and_both_track_and_speed_bind(bound: DriveBound) -> None:
    atan = physical_bound(P)
    assert bound.v_max == pytest.approx(float(no_load_speed(P))) and bound.v_max == pytest.approx(1.8)
    assert bound.x_lim == pytest.approx(1.25 * P.track)
    # not trivially low: well above what the firmware reaches (0.334 rad)
    assert 0.35 < bound.phi_max < atan
    # dropping either constraint raises it, dropping both leaves atan(a_max/g)
    assert bound.phi_max + 0.01 < bound.phi_max_no_track < atan - 0.05
    assert bound.phi_max + 0.01 < bound.phi_max_no_speed_limit < atan - 0.05
    assert bound.phi_max_a_only == pytest.approx(atan, abs=2e-4)
    # the maneuver at the bound: the drive's top speed reached, the whole track used
    assert bound.v_peak == pytest.approx(bound.v_max, abs=0.01)
    assert abs(bound.x_stop) == pytest.approx(bound.x_lim, abs=0.01)
    assert 0 < bound.t_brake < bound.t_stop < 1.5


@pytest.mark.slow
def test_bound_rises_without_the_drive_speed_limit(bound: DriveBound) -> None:
    fast = drive_bound(P.replace(V_supply=100 * P.V_supply))
    assert fast.v_max == pytest.approx(100 * bound.v_max)
    assert fast.phi_max > bound.phi_max + 0.01
    # a 180 m/s drive is as good as none: only the track and a_max remain
    assert fast.phi_max == pytest.approx(bound.phi_max_no_speed_limit, abs=1e-3)
    assert fast.phi_max_no_track == pytest.approx(physical_bound(P), abs=1e-3)


@pytest.mark.slow
def test_firmware_recovers_nothing_above_the_bound(bound: DriveBound) -> None:
    assert run_tilt(0.33).recovered  # the firmware's best (bench: 0.334 rad) ...
    assert 0.33 < bound.phi_max  # ... lies below the bound
    above = run_tilt(bound.phi_max + 0.02)
    assert not above.recovered


def test_max_effort_rights_just_below_the_bound_on_the_plant(bound: DriveBound) -> None:
    phi0, hold = bound.phi_max - 0.005, 0.5
    tr = max_effort(P, phi0, hold=hold)
    assert tr["ok"] == 1.0
    assert np.all(np.abs(tr["xddot"]) <= P.a_max + 1e-9) and np.all(np.abs(tr["duty"]) <= 1 + 1e-9)
    assert np.all(np.abs(tr["x"]) <= bound.x_lim)
    t_brake, t_stop = float(tr["t_brake"]), float(tr["t_stop"])

    # replay the rule on sim.plant with the motor's force range: a_max toward the fall (or
    # what full duty gives) until t_brake, a_max back until the cart stops, then hold it
    state = {"stopped": False}

    def rule(t: float, s: np.ndarray) -> float:
        if t >= t_brake and s[1] >= 0.0:
            state["stopped"] = True
        target = 0.0 if state["stopped"] else (-P.a_max if t < t_brake else P.a_max)
        a0 = dynamics(0.0, s, np.array([0.0]), P)[1]
        per_n = dynamics(0.0, s, np.array([1.0]), P)[1] - a0  # xddot is affine in the force
        lo, hi = force_limits(s[1], P)
        return float(np.clip((target - a0) / per_n, lo, hi))

    log = simulate(P, np.array([0.0, 0.0, phi0, 0.0]), t_stop + hold, controller=rule, dt=2.5e-4, substeps=1)
    X = np.stack([log["x"], log["xdot"], log["phi"], log["phidot"]])
    xdd = dynamics(0.0, X, log["force"], P)[1]
    assert np.max(np.abs(xdd)) <= P.a_max + 1e-6
    assert np.max(np.abs(log["x"])) <= bound.x_lim
    lo, hi = force_limits(log["xdot"], P)
    assert np.all((log["force"] >= lo - 1e-9) & (log["force"] <= hi + 1e-9))
    # the drive's speed limit is what caps the push: full duty, well under a_max
    assert np.any((np.abs(log["force"] - lo) < 1e-9) & (np.abs(xdd) < P.a_max - 1.0))
    k = int(np.argmax(log["t"] >= t_stop))
    assert abs(log["xdot"][k]) < 0.01 and log["x"][k] == pytest.approx(float(tr["x_stop"]), abs=0.01)
    # on the separatrix at the stop (the fall coordinate was phi0 = 0.37 at the start) ...
    ph = P.physical
    w0 = math.sqrt(ph["m"] * ph["g"] * ph["L"] / (ph["I"] + ph["m"] * ph["L"] ** 2))
    assert abs(2 * math.sin(log["phi"][k] / 2) + log["phidot"][k] / w0) < 0.01
    # ... and, the cart held, the pendulum rises into upright
    assert abs(log["phi"][-1]) < 0.05 and abs(log["phidot"][-1]) < 0.3 and abs(log["xdot"][-1]) < 0.01


def test_a_free_acceleration_profile_does_not_beat_the_bound(bound: DriveBound) -> None:
    # a coarse profile (12 intervals) started from a crude push-then-brake; the long run
    # (24 intervals, 4 starts) is quoted in drive_bound's docstring
    best = direct_search(P, n=12, starts=1)
    assert bound.phi_max - 0.005 < best <= bound.phi_max + 5e-4
