"""Plant realism (issue 24 item 1): dry friction, gear backlash, the H-bridge's deadband and
minimum duty, pot nonlinearity -- each does what physics says, in every simulator that must agree.

The models: docs/parameters.md, "Plant realism".  The defaults are the report's ideal robot
(every other test runs them unchanged); here each effect is switched on alone and checked
against the physics, then all together across the scenario simulator, the numpy batch reference
and the compiled kernel.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from host.design.discrete import controller_ss
from host.design.uncertainty import (UNCERTAINTY_REALISTIC, UncertaintyError, load_uncertainty,
                                     uncertainty_from_dict)
from sim import batch_kernel, motor
from sim.batch import BatchError, RunSet, closed_loop_iosys, simulate_batch
from sim.params import DEFAULT_PATH, REALISM_KEYS, ParamError, load_params, params_from_dict
from sim.plantsim import PlantSim, run_scenario_float
from sim.scenario import scenario_from_dict
from sim.sensors import SensorModel, adc_counts_per_rad, enc_counts_per_m, phi_to_adc

ROOT = Path(__file__).resolve().parents[1]
REALISTIC = ROOT / "sim" / "plants" / "realistic_cart.toml"
REAL = dict(coulomb=0.15, stiction=0.25, backlash=0.002, deadband=0.02, duty_min=0.01, pot_inl=0.004)


@pytest.fixture(scope="module")
def p():
    return load_params()


def _idle(sim: PlantSim, duty: int = 0) -> None:
    while not sim.done:
        sim.step(duty)


# ---------------------------------------------------------------- parameters
def test_defaults_are_the_ideal_robot(p) -> None:
    assert p.ideal and load_params(REALISTIC).ideal is False
    assert {k: v for k, v in p.realism.items() if k != "pot_inl_cycles"} == dict.fromkeys(
        ("coulomb", "stiction", "backlash", "deadband", "duty_min", "pot_inl"), 0.0)
    assert "coulomb" not in DEFAULT_PATH.read_text()  # the seed's file stays the seed's
    # all keys given as 0: the same run, bit for bit, as the file without them
    zero = p.replace(**{k.split(".", 1)[1]: (1.0 if k.endswith("cycles") else 0.0) for k in REALISM_KEYS})
    sc = scenario_from_dict({"name": "z", "duration": 0.4, "initial": {"phi": 0.05, "xdot": 0.1}})
    a, b = PlantSim(p, sc), PlantSim(zero, sc)
    for k in range(200):
        a.step(3000 - 30 * k)
        b.step(3000 - 30 * k)
    for col, v in a.result().items():
        assert np.array_equal(v, b.result()[col], equal_nan=True), col


@pytest.mark.parametrize("section, key, value", [
    ("cart", "coulomb", -0.1), ("cart", "stiction", "0.3"), ("motor", "backlash", 0.2),
    ("motor", "deadband", 0.6), ("motor", "duty_min", -0.01), ("sensors", "pot_inl", 0.2),
    ("sensors", "pot_inl_cycles", 0.0),
])
def test_a_bad_realism_value_names_its_key(p, section: str, key: str, value) -> None:
    data: dict = {}
    for k, v in p.values.items():
        sec, name = k.split(".", 1)
        if not (isinstance(v, float) and math.isnan(v)):
            data.setdefault(sec, {})[name] = v
    data[section][key] = value
    with pytest.raises(ParamError) as exc:
        params_from_dict(data)
    assert exc.value.key == f"{section}.{key}"
    assert str(exc.value).startswith(f"{section}.{key}: ")


# ---------------------------------------------------------------- each effect
def test_a_push_below_static_friction_does_not_move_the_cart(p) -> None:
    q = p.replace(coulomb=0.2, stiction=0.3)
    for amp, moves in ((0.29, False), (0.31, True)):
        sc = scenario_from_dict({"name": "s", "duration": 0.6, "force": [
            {"kind": "push", "start": 0.1, "duration": 0.4, "amplitude": amp}]})
        sim = PlantSim(q, sc)
        _idle(sim)
        x = sim.result()["x"]
        if moves:
            assert np.max(x) > 1e-4  # broke loose (0.01 N over the 0.3 N breakaway)
        else:
            assert np.all(x == 0.0) and sim.stuck  # not a micrometre


def test_coulomb_friction_decelerates_a_coasting_cart_linearly(p) -> None:
    # a cart with (almost) no motor back-EMF, no viscous friction and a feather of a pendulum:
    # only Coulomb friction acts, a = -coulomb / (M + m), until it stops -- and stays stopped
    q = p.replace(coulomb=0.2, b=0.0, kt=1e-7, m_cam=1e-6, m_shaft=1e-6)
    v0 = 0.3
    sim = PlantSim(q, scenario_from_dict({"name": "c", "duration": 1.2, "initial": {"xdot": v0}}))
    _idle(sim)
    log = sim.result()
    a = 0.2 / (q.M + q.m)
    t_stop = v0 / a
    sliding = log["t"] < t_stop - 0.003
    # within 1e-5 m/s (3e-5 of v0): the feather pendulum tips under the deceleration and its
    # reaction, ~1e-6 of the friction, adds up over the 0.75 s
    assert np.allclose(log["xdot"][sliding], v0 - a * log["t"][sliding], rtol=0, atol=1e-5)
    assert np.allclose(log["x"][sliding], v0 * log["t"][sliding] - 0.5 * a * log["t"][sliding] ** 2, atol=1e-5)
    after = log["t"] > t_stop + 0.003
    assert np.all(log["xdot"][after] == 0.0) and sim.stuck
    assert log["x"][-1] == pytest.approx(v0**2 / (2 * a), abs=1e-4)  # the stopping distance


def test_backlash_delays_the_force_reversal_and_the_motor_encoder_sees_the_play(p) -> None:
    # the cart held by static friction: the motor pushes it forward, then the duty reverses; the
    # motor crosses the play at its no-load speed before the force turns negative
    u, play = 0.1, 0.002
    duty = int(round(u * motor.DUTY_MAX))
    v0 = (duty / motor.DUTY_MAX) * p.V_supply * p.r_wheel / (p.kt * p.gear)  # no-load speed, m/s
    out = {}
    for bl in (0.0, play):
        q = p.replace(stiction=50.0, backlash=bl)
        sim = PlantSim(q, scenario_from_dict({"name": "b", "duration": 0.2}))
        for _ in range(50):
            sim.step(duty)
        for _ in range(50):
            sim.step(-duty)
        out[bl] = sim.result()
    F0, F1 = out[0.0]["force"], out[play]["force"]
    assert np.all(F0[:50] > 0) and np.all(F0[50:] < 0)  # no play: the force follows the duty at once
    zero = np.flatnonzero(F1[50:] == 0.0)
    assert F1[49] > 0 and zero[0] == 0 and np.all(F1[50 + zero[-1] + 1:] < 0)
    ticks = zero[-1] + 1  # ticks without force after the reversal: the play crossed at v0
    assert abs(ticks * 0.002 - play / v0) <= 0.002 + 1e-9
    assert np.all(out[play]["x"] == 0.0)  # the cart never moved ...
    cpm = enc_counts_per_m(p)
    enc = out[play]["enc"].astype(np.int64)
    enc = np.where(enc > 32767, enc - 65536, enc)
    assert enc[45] == round(0.5 * play * cpm) and enc[-1] == round(-0.5 * play * cpm)  # ... the motor did


def test_a_duty_below_the_deadband_gives_no_force(p) -> None:
    q = p.replace(deadband=0.02)
    db = 0.02 * motor.DUTY_MAX
    for duty in (100, 600, -650):
        sim = PlantSim(q, scenario_from_dict({"name": "d", "duration": 0.2}))
        _idle(sim, duty)
        log = sim.result()
        assert np.all(log["force"] == 0.0) and np.all(log["x"] == 0.0)
        assert float(motor.force_from_duty(duty, 0.0, q)) == 0.0
    # above it the bridge applies the duty less the deadband
    assert float(motor.force_from_duty(2000, 0.0, q)) == pytest.approx(
        float(motor.force_from_duty(2000 - db, 0.0, p)), rel=1e-12)
    assert float(motor.force_from_duty(-2000, 0.0, q)) == pytest.approx(
        -float(motor.force_from_duty(2000 - db, 0.0, p)), rel=1e-12)


def test_a_pulse_below_the_minimum_duty_applies_nothing(p) -> None:
    q = p.replace(duty_min=0.01)
    assert float(motor.force_from_duty(300, 0.0, q)) == 0.0
    assert float(motor.force_from_duty(-320, 0.0, q)) == 0.0
    assert float(motor.force_from_duty(400, 0.0, q)) == float(motor.force_from_duty(400, 0.0, p))  # no offset
    # at a moving cart a zero pulse brakes like the ideal bridge at duty 0 (back-EMF current)
    assert float(motor.force_from_duty(300, 0.2, q)) == float(motor.force_from_duty(0, 0.2, p)) < 0


def test_pot_nonlinearity_shows_in_the_reading(p) -> None:
    q = p.replace(pot_inl=0.005)
    phis = np.linspace(-1.2, 1.2, 97)
    ideal = phi_to_adc(phis, p)
    real = phi_to_adc(phis, q)
    lin = p.pot_offset + phis * adc_counts_per_rad(p)
    want = np.rint(lin + 0.005 * 4096 * np.sin(2 * np.pi * lin / 4096))
    assert np.array_equal(real, want)
    assert 20 <= int(np.max(np.abs(real - ideal))) <= 21  # 20.5 counts at the sine's peaks, rounded
    assert phi_to_adc(0.0, q) == p.pot_offset  # zero at mid-travel (one period over the full scale)
    # the scenario simulator reads the same counts (its scalar path)
    sm = SensorModel(q)
    assert [sm.quantise(0.0, float(v))[1] for v in phis] == real.tolist()
    bow = p.replace(pot_inl=0.005, pot_inl_cycles=0.5)
    assert phi_to_adc(0.0, bow) == p.pot_offset + 20  # a bow: the upright reading moves


# ---------------------------------------------------------------- the simulators agree
def _real_runs(p, n: int, seed: int = 3) -> RunSet:
    rng = np.random.default_rng(seed)
    x0 = np.zeros((n, 4))
    x0[:, 2] = rng.uniform(-0.3, 0.3, n)  # some fall
    x0[n // 3:, 1] = rng.uniform(-0.1, 0.1, n - n // 3)  # some start sliding, the others stuck
    vals = {"coulomb": rng.uniform(0, 0.4, n), "stiction": rng.uniform(0, 0.6, n),
            "backlash": rng.uniform(0, 0.004, n), "deadband": rng.uniform(0, 0.04, n),
            "duty_min": rng.uniform(0, 0.02, n), "pot_inl": rng.uniform(-0.01, 0.01, n),
            "M": p.M * rng.uniform(0.8, 1.2, n), "kt": p.kt * rng.uniform(0.9, 1.1, n)}
    for i, k in enumerate(vals):
        if k in REAL:
            vals[k][i::7] = 0.0  # every effect off in some runs
    vals["coulomb"][::5] = vals["stiction"][::5] = vals["backlash"][::5] = vals["deadband"][::5] = 0.0
    vals["duty_min"][::5] = vals["pot_inl"][::5] = 0.0  # and every fifth run ideal
    return RunSet(x0=x0, values=vals, delay_ticks=rng.integers(0, 8, n), noise_seed=rng.integers(0, 2**62, n),
                  x_ref=rng.uniform(-0.1, 0.1, n))


@pytest.mark.skipif(not batch_kernel.AVAILABLE, reason="numba not installed")
@pytest.mark.parametrize("accel, drive, u_max", [(None, "motor", None), (5.0, "motor", 0.8), (None, "force", None)],
                         ids=["motor", "accel-clip-saturated", "force-drive"])
def test_kernel_is_bit_identical_to_numpy_with_plant_realism(p, accel, drive, u_max) -> None:
    from sim.sensors import NoiseModel

    runs = _real_runs(p, 100)
    ctrl = controller_ss(p, u_max=u_max) if u_max is not None else controller_ss(p)
    kw = dict(duration=0.8, noise=NoiseModel("uniform", amplitude=0.002), accel_limit=accel, drive=drive, record=True)
    a = simulate_batch(p, ctrl, runs, engine="numpy", **kw)
    b = simulate_batch(p, ctrl, runs, engine="numba", **kw)
    for k in a.metrics:
        assert np.array_equal(a.metrics[k], b.metrics[k]), k
    for k in a.traces:
        assert np.array_equal(a.traces[k], b.traces[k]), k
    if drive == "motor":  # the effects were on: some runs stuck a while, some duty in the dead zone
        assert np.any(a.traces["xdot"][1:] == 0.0) and np.any((a.traces["force"] == 0.0) & (a.traces["duty"] != 0))


@pytest.mark.parametrize("engine", ["numpy", pytest.param("numba", marks=pytest.mark.skipif(
    not batch_kernel.AVAILABLE, reason="numba not installed"))])
def test_an_ideal_run_is_the_same_in_a_batch_with_plant_realism(p, engine) -> None:
    # chunk independence (the Dask scale-out): the realism code path leaves an ideal run's bits alone
    runs = _real_runs(p, 20)
    ideal = np.flatnonzero(np.all([runs.values[k] == 0.0 for k in REAL], axis=0))
    assert len(ideal) >= 3
    ctrl = controller_ss(p)
    mixed = simulate_batch(p, ctrl, runs, duration=0.6, record=True, engine=engine)
    alone = simulate_batch(p, ctrl, runs.subset(ideal), duration=0.6, record=True, engine=engine)
    for k in alone.metrics:
        assert np.array_equal(mixed.metrics[k][ideal], alone.metrics[k]), k
    for k in ("x", "phi", "duty", "force"):
        assert np.array_equal(mixed.traces[k][:, ideal], alone.traces[k]), k


@pytest.mark.parametrize("kind", ["tilt", "step"])
def test_scenario_simulator_and_batch_agree_with_plant_realism(p, kind: str) -> None:
    ctrl = controller_ss(p)
    q = p.replace(**REAL)
    d = {"initial": {"phi": 0.1}} if kind == "tilt" else {"reference": {"kind": "step", "start": 0.0, "amplitude": 0.2}}
    sc = scenario_from_dict({"name": kind, "duration": 3.0, **d})
    log = run_scenario_float(sc, p, ctrl, plant=q)
    runs = RunSet(x0=np.array([[0.0, 0.0, 0.1 if kind == "tilt" else 0.0, 0.0]]),
                  values={k: [v] for k, v in REAL.items()}, delay_ticks=np.array([5]),
                  x_ref=0.0 if kind == "tilt" else 0.2)
    tr = simulate_batch(p, ctrl, runs, duration=3.0, record=True, engine="numpy").traces
    n = len(log["x"])
    # the same duties every tick; the states to rounding (different but equivalent expressions)
    assert np.array_equal(tr["duty"][:n, 0], log["duty"])
    assert np.max(np.abs(tr["x"][:n, 0] - log["x"])) < 1e-8
    assert np.max(np.abs(tr["phi"][:n, 0] - log["phi"])) < 1e-8
    ideal = run_scenario_float(sc, p, ctrl)
    assert np.max(np.abs(ideal["x"] - log["x"])) > 0.01  # and the effects are not negligible


def test_batch_refuses_bad_realism_and_the_iosys_reference_the_ideal_only(p) -> None:
    with pytest.raises(BatchError, match="backlash"):
        RunSet(x0=np.zeros((2, 4)), values={"backlash": [0.0, 0.2]})
    runs = RunSet(x0=np.zeros((1, 4)), values={"coulomb": [0.1]})
    with pytest.raises(BatchError, match="coulomb"):
        closed_loop_iosys(p, controller_ss(p), runs.true_params(p, 0), 5)


# ---------------------------------------------------------------- the uncertainty sets
def test_realistic_uncertainty_set_loads_and_places_the_realism(p) -> None:
    base = load_uncertainty()
    real = load_uncertainty(UNCERTAINTY_REALISTIC)
    assert base.realism == {} and set(real.realism) == {"coulomb", "stiction", "backlash", "deadband", "duty_min",
                                                        "pot_inl"}
    pb, pr = base.points(p.rate, p.delay), real.points(p.rate, p.delay)
    assert len(pb) == len(pr) == 1 + 128 + 32
    # the same box and random draws as today's set; realism nearest 0 at the nominal point, at the
    # high end at every vertex, inside the ranges elsewhere
    for a, b in zip(pb, pr):
        assert a.factors == b.factors and a.delay_ticks == b.delay_ticks and a.realism == {}
    assert all(v == 0.0 for v in pr[0].realism.values())
    assert all(pt.realism == {k: hi for k, (lo, hi) in real.realism.items()} for pt in pr if pt.vertex)
    for pt in pr[129:]:
        assert all(real.realism[k][0] <= v <= real.realism[k][1] for k, v in pt.realism.items())
    # a point's robot carries the realism: robot-file overrides and batch values
    corner = pr[1]
    assert corner.overrides(p)["cart.coulomb"] == 0.5 and corner.values(p)["backlash"] == 0.003
    p.replace(**corner.overrides(p))  # a valid robot
    RunSet(x0=np.zeros((1, 4)), values={k: [v] for k, v in corner.values(p).items()})
    assert "coulomb 0.5" in corner.label(p.rate)
    every = uncertainty_from_dict({"realism_vertices": "all", "realism": {"coulomb": [0.0, 0.5]}}, "<t>", base)
    assert len(every.points(p.rate, p.delay)) == 1 + 256 + 32


@pytest.mark.parametrize("data, key", [
    ({"realism": {"friction": [0, 1]}}, "realism.friction"),
    ({"realism": {"coulomb": [0.5, 0.1]}}, "realism.coulomb"),
    ({"realism": {"pot_inl": [-0.5, 0.1]}}, "realism.pot_inl"),
    ({"realism": {"deadband": 0.02}}, "realism.deadband"),
    ({"realism": [1, 2]}, "realism"),
    ({"realism_vertices": "some"}, "realism_vertices"),
])
def test_a_bad_realism_range_names_its_key(data, key: str) -> None:
    with pytest.raises(UncertaintyError) as exc:
        uncertainty_from_dict(data, "<test>", load_uncertainty())
    assert exc.value.key == key


# ---------------------------------------------------------------- the command line
def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "host.cli.main", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=600)


@pytest.mark.slow
def test_simulate_runs_the_realistic_plant(tmp_path: Path) -> None:
    csv = tmp_path / "real.csv"
    r = _cli("simulate", "--scenario", "ref_step_20cm", "--plant", str(REALISTIC), "--csv", str(csv), cwd=ROOT)
    assert r.returncode in (0, 1), r.stderr  # 1: a constraint the realistic cart misses (a limit cycle)
    assert "differs in: cart.coulomb, cart.stiction, motor.backlash, motor.deadband, motor.duty_min, " \
           "sensors.pot_inl" in r.stderr
    assert "ref_step_20cm" in r.stdout + r.stderr
    ideal = tmp_path / "ideal.csv"
    assert _cli("simulate", "--scenario", "ref_step_20cm", "--csv", str(ideal), cwd=ROOT).returncode == 0
    from sim.plantsim import read_csv

    a, b = read_csv(csv), read_csv(ideal)
    assert len(a["x"]) == len(b["x"]) and np.max(np.abs(a["x"] - b["x"])) > 0.01


def replay_matches(csv: Path, scenario: dict) -> None:
    """The HIL log is the realistic plant's: the scenario simulator, fed the board's duties, reads
    exactly the counts the board got (ADC with the pot's nonlinearity, the motor encoder)."""
    from sim.plantsim import read_csv

    log = read_csv(csv)
    n = int(round(scenario["duration"] * 500))
    assert len(log["t"]) == n and np.all(np.isfinite(log["phi"]))
    sim = PlantSim(load_params(REALISTIC), scenario_from_dict(scenario))
    for d in log["duty"].astype(int):
        assert sim.read() == (int(log["adc"][sim.tick]), int(log["enc"][sim.tick])), sim.tick
        sim.step(int(d))
    assert np.array_equal(sim.result()["x"], log["x"])


SHORT = {"name": "short_tilt", "duration": 1.0, "initial": {"phi": 0.05}}
SHORT_TOML = 'name = "short_tilt"\nduration = 1.0\n[initial]\nphi = 0.05\n'


@pytest.mark.slow
def test_hil_virtual_runs_the_realistic_plant(tmp_path: Path) -> None:
    sc = tmp_path / "short_tilt.toml"
    sc.write_text(SHORT_TOML)
    out = tmp_path / "hil"
    r = _cli("hil", "--virtual", "--plant", str(REALISTIC), "--scenario", str(sc), "--out", str(out), "--no-plots",
             "--no-compare", "--quiet", cwd=ROOT)
    assert r.returncode in (0, 1), r.stderr
    assert "differs in: cart.coulomb" in r.stderr
    replay_matches(out / "short_tilt.csv", SHORT)
