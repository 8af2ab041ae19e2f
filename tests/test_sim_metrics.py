"""Metrics on synthetic signals with known answers, constraint checks, the summary table."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.metrics import Metrics, check_constraints, compute_metrics, settling_time, summary_table, RunSummary
from sim.params import load_params
from sim.scenario import scenario_from_dict

DT = 0.002


def _log(t: np.ndarray, **cols: np.ndarray) -> dict[str, np.ndarray]:
    z = np.zeros_like(t)
    base = {"t": t, "x": z, "phi": z, "x_ref": z, "xddot": z, "force": z, "duty": np.zeros(t.size, dtype=np.int64)}
    base.update(cols)
    return base


def test_settling_of_exponential() -> None:
    tau = 0.3
    t = np.arange(0, 5, DT)
    s = np.exp(-t / tau)
    ts = settling_time(t, s, final=0.0)
    assert ts == pytest.approx(tau * math.log(50), abs=DT)
    # floor widens the band; an always-inside signal settles at 0; a signal outside at the end has not settled
    assert settling_time(t, s, final=0.0, floor=0.1) == pytest.approx(tau * math.log(10), abs=DT)
    assert settling_time(t, 0.001 * s, final=0.0, floor=0.01) == 0.0
    assert math.isnan(settling_time(t, np.sin(3 * t), final=0.0))
    # segment: a response starting at 1 s is measured from 1 s
    s2 = np.where(t >= 1, np.exp(-(t - 1) / tau), 0.0)
    assert settling_time(t, s2, t0=1.0, final=0.0) == pytest.approx(tau * math.log(50), abs=DT)


def test_settling_of_damped_oscillation_uses_envelope() -> None:
    t = np.arange(0, 10, DT)
    zeta, wn = 0.2, 6.0
    wd = wn * math.sqrt(1 - zeta**2)
    s = np.exp(-zeta * wn * t) * np.cos(wd * t)
    ts = settling_time(t, s, final=0.0)
    bound = math.log(50) / (zeta * wn)  # envelope crosses 2 %
    assert bound - 2 * math.pi / wd <= ts <= bound + DT


def test_metrics_of_synthetic_tilt_run() -> None:
    p = load_params()
    sc = scenario_from_dict({"name": "syn", "duration": 5.0, "initial": {"phi": 0.2}})
    t = np.arange(0, 5, DT)
    phi = 0.2 * np.exp(-2 * t) * np.cos(4 * t)
    duty = np.where(t < 0.1, 32767, 1000)
    log = _log(t, phi=phi, xddot=6 * np.sin(t), force=-3 * np.cos(t), duty=duty, x=np.full_like(t, 0.01))
    m = compute_metrics(log, sc, p)
    assert m.peak_phi == pytest.approx(0.2)
    assert m.peak_xddot == pytest.approx(6.0, rel=1e-4)
    assert m.peak_force == pytest.approx(3.0)
    assert m.time_saturated == pytest.approx(0.1, abs=DT)
    assert m.rms_phi == pytest.approx(np.sqrt(np.mean(phi**2)))
    assert m.ss_cart_error == pytest.approx(0.01)
    # first swing through upright: min of 0.2 e^{-2t} cos 4t at 4t = pi (approx) -> ~ e^{-pi/2}
    assert m.overshoot == pytest.approx(100 * float(-phi.min()) / 0.2)
    assert 15 < m.overshoot < 25
    checks = {c.name: c for c in check_constraints(m, p, sc)}
    assert checks["phi_max"].status == "PASS"
    assert checks["a_max"].status == "FAIL" and not checks["a_max"].as_expected
    assert checks["settle"].status == ("PASS" if m.settling_time < 2.5 else "FAIL")


def test_metrics_of_reference_step() -> None:
    p = load_params()
    sc = scenario_from_dict({"name": "st", "duration": 4.0,
                             "reference": {"kind": "step", "start": 1.0, "amplitude": 0.2}})
    t = np.arange(0, 4, DT)
    tt = np.clip(t - 1.0, 0, None)
    x = np.where(t >= 1.0, 0.2 * (1 - np.exp(-3 * tt) * (np.cos(5 * tt) + 0.6 * np.sin(5 * tt))), 0.0)
    log = _log(t, x=x, x_ref=sc.x_ref(t))
    m = compute_metrics(log, sc, p)
    assert m.overshoot == pytest.approx(100 * (x.max() - 0.2) / 0.2, rel=1e-6)
    assert m.overshoot > 1
    # x settles in the 2 % band of the 0.2 m step: 4 mm
    expect = settling_time(t, x, t0=1.0, t1=4.0, scale=0.2, floor=2 * 2 * math.pi * p.r_wheel / p.enc_cpr)
    assert m.settling_time == pytest.approx(expect)
    assert 0.5 < m.settling_time < 2.0


def test_noise_run_has_no_settling_time() -> None:
    p = load_params()
    sc = scenario_from_dict({"name": "n", "duration": 2.0, "noise": {"kind": "uniform", "amplitude": 0.01}})
    t = np.arange(0, 2, DT)
    rng = np.random.default_rng(0)
    log = _log(t, phi=0.01 * rng.standard_normal(t.size))
    m = compute_metrics(log, sc, p)
    assert math.isnan(m.settling_time) and math.isnan(m.overshoot)
    assert m.rms_phi == pytest.approx(0.01, rel=0.1)
    c = {c.name: c for c in check_constraints(m, p, sc)}
    assert c["settle"].status == "N/A"


def test_summary_table_marks() -> None:
    p = load_params()
    ok = Metrics(1.0, 0.1, 5.0, 2.0, 3.0, 0.0, 0.01, 0.001, 5.0)
    bad = Metrics(math.nan, 0.4, 5.0, 20.0, 30.0, 0.5, 0.1, 0.001, 5.0)
    sc = scenario_from_dict({"name": "b", "duration": 5.0, "expect": {"a_max": "fail", "note": "why"}})
    runs = [RunSummary("good", ok, check_constraints(ok, p)), RunSummary("bad", bad, check_constraints(bad, p, sc))]
    text = summary_table(runs, title="T")
    lines = text.splitlines()
    assert lines[0] == "T" and "|phi|<0.3" in lines[1] and "|a|<=5" in lines[1]
    good = next(line for line in lines if line.startswith("good"))
    assert good.count("PASS") == 3
    badl = next(line for line in lines if line.startswith("bad"))
    assert "FAIL!" in badl and "FAIL*" in badl  # unexpected phi/settle, expected a_max
    assert "3 constraint FAIL(s) (1 expected" in lines[-1]
    assert runs[0].passed and not runs[1].passed and not runs[1].as_expected
    runs[1] = RunSummary("bad", bad, runs[1].checks, "a long explanation " * 10)
    with_notes = summary_table(runs, notes=True).splitlines()
    assert with_notes[-3].startswith("* bad: a long explanation") and all(len(x) <= 100 for x in with_notes[-3:])
    d = runs[1].as_dict()
    assert d["checks"][2]["as_expected"] is True and d["metrics"]["peak_phi"] == 0.4
    import json

    json.dumps(d)


def test_overshoot_when_the_run_starts_on_the_other_side() -> None:
    """A small opposite swing at t = 0 (below a tenth of the peak) is not the first peak's end:
    the first peak is the excursion's, the overshoot its opposite swing (this raised on an
    empty slice before)."""
    p = load_params()
    sc = scenario_from_dict({"name": "syn", "duration": 5.0})
    t = np.arange(0, 5, DT)
    phi = np.where(t < 0.05, -0.001, 0.1 * np.exp(-1.5 * (t - 0.05)) * np.cos(5 * (t - 0.05)))
    m = compute_metrics(_log(t, phi=phi), sc, p)
    opp = float(np.max(-phi[t >= 0.05]))
    assert m.overshoot == pytest.approx(100.0 * opp / 0.1, rel=1e-6)
