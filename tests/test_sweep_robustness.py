"""Sweeps: per-run seeding, constraint checks, worst-case scenarios that replay, tune, tilt."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sim.batch import simulate_batch
from sim.params import load_params
from sim.scenario import dump_scenario, load_scenario
from host.studies.sweep import (
    Design,
    SweepConfig,
    SweepError,
    Uncertainty,
    checks,
    concat,
    design_grid,
    design_random,
    pareto_front,
    physical_tilt_limit,
    robustness,
    run_task,
    runset_from_scenario,
    sample_runs,
    summarise,
    tasks_for,
    tilt,
    tune,
    worst_case_scenarios,
    worst_cases,
)


@pytest.fixture(scope="module")
def p():
    return load_params()


@pytest.fixture(scope="module")
def cfg(p):
    return SweepConfig(params=p, seed=7, duration=1.5)


@pytest.fixture(scope="module")
def table(cfg):
    return robustness(cfg, 12, chunk=5)


def test_runs_are_seeded_per_run_not_per_chunk(cfg, table) -> None:
    again = concat([run_task(cfg, 0, 7), run_task(cfg, 7, 12)])
    assert set(again) == set(table)
    for k in table:
        assert np.array_equal(again[k], table[k]), k
    # another seed gives other robots
    other, _ = sample_runs(replace(cfg, seed=8), 0, 12)
    assert not np.array_equal(other.values["M"], sample_runs(cfg, 0, 12)[0].values["M"])


def test_draws_stay_in_their_ranges(p, cfg, table) -> None:
    u = cfg.uncertainty
    assert np.all(np.abs(table["M"] / p.M - 1) <= u.mass + 1e-12)
    assert np.all(np.abs(table["m_cam"] / p.m_cam - 1) <= u.mass + 1e-12)
    assert np.allclose(table["m_cam"] / p.m_cam, table["m_shaft"] / p.m_shaft)
    assert np.all((table["b"] >= p.b * u.friction[0] - 1e-12) & (table["b"] <= p.b * u.friction[1] + 1e-12))
    assert np.all(np.abs(table["R"] / p.R - 1) <= u.motor + 1e-12)
    assert np.all((table["delay"] >= 0.004 - 1e-12) & (table["delay"] <= 0.020 + 1e-12))
    assert np.all(np.abs(table["phi0"]) <= u.tilt)
    assert len(np.unique(table["noise_seed"])) == len(table["run"])


def test_checks_follow_the_constraints(p) -> None:
    m = {"phi_max": np.array([0.1, 0.31, 0.1, 0.1, 0.1]), "settle": np.array([1.0, 1.0, 2.6, np.inf, 1.0]),
         "xddot_max": np.array([5.0, 1.0, 1.0, 1.0, 5.01]), "fallen": np.array([False, False, False, False, False])}
    c = checks(m, p)
    assert list(c["success"]) == [True, False, False, False, False]
    assert list(c["ok_phi"]) == [True, False, True, True, True]
    assert list(c["ok_accel"]) == [True, True, True, True, False]
    assert c["worst_ratio"][0] == pytest.approx(1.0)
    assert np.isinf(c["worst_ratio"][3])


def test_summary_rates(table) -> None:
    s = summarise(table)
    assert s["runs"] == 12
    assert s["success_rate"] == pytest.approx(np.mean(table["success"]))
    assert s["phi_max_p5"] <= s["phi_max_p50"] <= s["phi_max_p95"] <= s["phi_max_max"]


def test_worst_case_scenario_replays_exactly(p, cfg, table, tmp_path) -> None:
    worst = worst_cases(table, 2)
    assert table["worst_ratio"][worst[0]] == np.max(table["worst_ratio"])
    scen = worst_case_scenarios(cfg, table, 2)
    ctrl = cfg.design.controller(p)
    for s, i in zip(scen, worst):
        path = tmp_path / f"{s.name}.toml"
        path.write_text(dump_scenario(s))
        back = load_scenario(path)
        assert back == replace(s, source=str(path))
        m = simulate_batch(p, ctrl, runset_from_scenario(back, p), duration=back.duration, noise=back.noise).metrics
        for k in ("phi_max", "settle", "xddot_max", "force_max", "phi_rms"):
            assert m[k][0] == table[k][i], k
        assert back.expect.a_max == ("pass" if table["ok_accel"][i] else "fail")


def test_replay_refuses_what_the_batch_cannot_do(p) -> None:
    s = load_scenario("push_0p2N_5s")
    with pytest.raises(SweepError, match="forces"):
        runset_from_scenario(s, p)


def test_bad_sweep_inputs(p) -> None:
    with pytest.raises(SweepError):
        Uncertainty(mass=1.5)
    with pytest.raises(SweepError):
        Uncertainty(delay=(0.02, 0.01))
    with pytest.raises(SweepError):
        SweepConfig(params=p, seed=-1)
    with pytest.raises(SweepError):
        tasks_for(SweepConfig(params=p), 0)
    with pytest.raises(SweepError):
        Design(observer=0.0).controller(p)


def test_pareto_front() -> None:
    pts = [(1, 1, 1), (2, 2, 2), (0.5, 3, 1), (1, 1, 1.5), (3, 0.1, 5)]
    assert pareto_front(pts) == {0, 2, 4}


def test_design_generators() -> None:
    g = design_grid(q_x=(1.0, 2.0), q_phi=(0.5,), r=(0.01,), observer=(1.0, 2.0))
    assert [d.Q for d in g] == [(1.0, 0.0, 0.5, 0.0)] * 2 + [(2.0, 0.0, 0.5, 0.0)] * 2
    assert len({d.name for d in g}) == 4
    a, b = design_random(5, seed=1), design_random(5, seed=1)
    assert a == b and len({d.name for d in a}) == 5


def test_tune_scores_designs_on_the_same_runs(p) -> None:
    cfg = SweepConfig(params=p, seed=3, duration=1.0)
    designs = [Design("soft", Q=(1.0, 0.0, 0.8, 0.0), R=0.1), Design("report"), Design("bad", Q=(1.0, 0.0, 1.0, 0.0), R=-1.0)]
    rows, t = tune(cfg, designs, 4, chunk=3)
    by = {r["design"]: r for r in rows}
    assert by["bad"]["error"] and not by["bad"]["pareto"]
    assert 0.0 <= by["soft"]["success_rate"] <= 1.0
    assert len(t["run"]) == 8
    # common random numbers: both designs saw the same robots
    soft, rep = t["design"] == "soft", t["design"] == "report"
    assert np.array_equal(t["M"][soft], t["M"][rep]) and np.array_equal(t["noise_seed"][soft], t["noise_seed"][rep])
    # the softer design asks for less force
    assert by["soft"]["force_max_p50"] < by["report"]["force_max_p50"]
    assert any(r["pareto"] for r in rows)


def test_tilt_limits(p) -> None:
    assert physical_tilt_limit(p) == pytest.approx(math.atan(5.0 / 9.8))
    rows, t = tilt(p, [Design("soft", R=1.0), Design("report")], step=0.1, hi=0.5, duration=5.0)
    soft, rep = rows
    assert 0.2 <= soft["tilt_max"] < physical_tilt_limit(p)  # recovers well, never beyond physics
    assert rep["tilt_max"] < soft["tilt_max"]  # the aggressive design saturates and loses it
    assert t["xddot_max"].max() <= p.a_max + 1e-9
    assert soft["tilt_max_deg"] == pytest.approx(math.degrees(soft["tilt_max"]))


def test_tune_table_does_not_depend_on_chunking(p) -> None:
    cfg = SweepConfig(params=p, seed=9, duration=0.4)
    designs = [Design("a", R=0.1), Design("b"), Design("c", observer=3.0)]
    r1, t1 = tune(cfg, designs, 3, chunk=2)
    r2, t2 = tune(cfg, designs, 3, chunk=100)
    assert r1 == r2
    assert all(np.array_equal(t1[k], t2[k]) for k in t1)
    with pytest.raises(SweepError, match="unique"):
        tune(cfg, [Design("a"), Design("a", R=0.1)], 2)
