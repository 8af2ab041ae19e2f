"""``--plant FILE``: the simulated robot differs from the design, everywhere (issue 15 item 1).

The firmware designed from ``sim/robot.toml`` runs on a plant whose pivot inertia is 0.7 of
the model's; the precedence rule (design < plant file < scenario) is printed with the keys a
scenario overrides; delays that are not whole sensor samples are refused by the library.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from host.cli.main import main
from sim.params import DEFAULT_PATH, ParamError, load_params, plant_params
from sim.scenario import PRECEDENCE, load_scenario, precedence_note, scenario_from_dict
from sim.sensors import SensorModel, delay_steps

ROOT = Path(__file__).resolve().parents[1]


def _robot(tmp_path: Path, name: str, section: str, line: str) -> Path:
    text = DEFAULT_PATH.read_text().replace(f"[{section}]\n", f"[{section}]\n{line}\n", 1)
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.fixture()
def soft(tmp_path: Path) -> Path:
    """The report's robot with the pivot inertia at 0.7 of the model's."""
    return _robot(tmp_path, "soft.toml", "pendulum", f"I = {0.7 * load_params().I!r}")


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "host.cli.main", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)


# ------------------------------------------------------------------ library
def test_plant_params_keeps_the_design_rate_and_constraints(tmp_path: Path) -> None:
    design = load_params()
    fast = load_params(_robot(tmp_path, "fast.toml", "loop", "").as_posix())
    assert plant_params(design, fast) == (fast, [])
    text = DEFAULT_PATH.read_text().replace("a_max = 5.0", "a_max = 9.0")
    (tmp_path / "a.toml").write_text(text)
    a = load_params(tmp_path / "a.toml")
    if a.a_max == design.a_max:
        pytest.skip("robot.toml spells a_max differently")
    p, notes = plant_params(design, a)
    assert p.a_max == design.a_max and any("loop.a_max" in n for n in notes)
    text = DEFAULT_PATH.read_text()
    rate = int(design.rate)
    (tmp_path / "r.toml").write_text(text.replace(f"rate = {rate}", f"rate = {2 * rate}"))
    r = load_params(tmp_path / "r.toml")
    if r.rate != design.rate:
        with pytest.raises(ParamError, match="loop.rate"):
            plant_params(design, r)


def test_precedence_note_names_the_rule_and_the_overridden_keys(soft: Path) -> None:
    plant = load_params(soft)
    sc = scenario_from_dict({"name": "s", "duration": 1.0, "params": {"M": 0.55, "I": 0.02}, "sensors": {"delay": 0.004}})
    note = precedence_note(sc, plant)
    assert note is not None and note.startswith(PRECEDENCE)
    assert "cart.M" in note and "-> 0.55" in note and "pendulum.I" in note and "sensors.delay" in note
    assert precedence_note(load_scenario("tilt_0p1"), plant) is None
    # the scenario wins: its [params] go on top of the plant file
    assert sc.apply(plant).M == 0.55 and sc.apply(plant).I == 0.02


def test_a_delay_between_sensor_samples_is_refused_not_rounded() -> None:
    assert delay_steps(0.01, 500) == 5 and delay_steps(0.0, 500) == 0
    for bad in (0.0105, 0.003, 0.0011):
        with pytest.raises(ValueError, match="not a whole number of sensor samples"):
            delay_steps(bad, 500)
    with pytest.raises(ValueError, match="whole number"):
        SensorModel(load_params(), delay=0.0031)


def test_float_simulation_of_the_plant_differs_and_the_firmware_side_keeps_the_design(soft: Path) -> None:
    from host.design.discrete import controller_for
    from sim.plantsim import run_scenario_float

    p, plant = load_params(), load_params(soft)
    sc = load_scenario("ref_step_20cm")
    ctrl = controller_for(sc, p)
    nom = run_scenario_float(sc, p, ctrl, init="measured")
    same = run_scenario_float(sc, p, ctrl, init="measured", plant=p)
    off = run_scenario_float(sc, p, ctrl, init="measured", plant=plant)
    assert np.array_equal(nom["phi"], same["phi"])
    assert not np.allclose(nom["phi"], off["phi"], atol=1e-4)


# ------------------------------------------------------------------ CLI
@pytest.mark.slow
def test_hil_plant_runs_the_shipped_firmware_on_another_robot(soft: Path, tmp_path: Path) -> None:
    args = ("hil", "--virtual", "--scenario", "ref_step_20cm", "--no-plots", "--quiet")
    nominal = _cli(*args, "--out", str(tmp_path / "n"), "--json", str(tmp_path / "n.json"))
    assert nominal.returncode == 0, nominal.stdout + nominal.stderr
    off = _cli(*args, "--out", str(tmp_path / "p"), "--json", str(tmp_path / "p.json"), "--plant", str(soft))
    assert f"plant: {soft}" in off.stderr and "differs in: pendulum.I" in off.stderr
    (a,), (b,) = (json.loads((tmp_path / f).read_text()) for f in ("n.json", "p.json"))
    for rec in (a, b):
        assert {"name", "passed", "phi_max", "settle_s", "accel_max"} <= set(rec)
        assert rec["name"] == "ref_step_20cm"
    assert (a["phi_max"], a["settle_s"], a["accel_max"]) != (b["phi_max"], b["settle_s"], b["accel_max"])
    # the finding was that the 30 % softer pendulum missed the 2.5 s settling on the 20 cm
    # step with the default of then (Q = diag(1.5, 0, 0.1, 0.02)); the robust default shipped since
    # meets it there, later than on the nominal robot (measured 1.95 s and 2.32 s)
    assert a["passed"] and a["settle_s"] < 2.5
    assert b["passed"] and a["settle_s"] + 0.1 < b["settle_s"] <= 2.5 and off.returncode == 0
    # HIL and the float reference of the same plant agree (the firmware side keeps the design)
    assert b["dphi_vs_float"] is not None and b["dphi_vs_float"] < 0.01


@pytest.mark.slow  # 3-5 s on the loaded 2-core machine: out of the fast loop
def test_hil_plant_prints_the_precedence_when_a_scenario_overrides(soft: Path, tmp_path: Path) -> None:
    sc = tmp_path / "heavy.toml"
    sc.write_text('name = "heavy"\nduration = 1.0\n[initial]\nphi = 0.05\n[params]\nM = 0.55\n[expect]\nsettle = "any"\n')
    r = _cli("hil", "--virtual", "--scenario", str(sc), "--no-plots", "--quiet", "--out", str(tmp_path / "o"),
             "--plant", str(soft))
    assert r.returncode == 0, r.stdout + r.stderr
    assert PRECEDENCE in r.stderr and "cart.M 0.5 -> 0.55" in r.stderr


def test_simulate_accepts_plant_and_prints_the_precedence(soft: Path, tmp_path: Path, capsys) -> None:
    sc = tmp_path / "step.toml"
    sc.write_text('name = "step"\nduration = 3.0\n[reference]\nkind = "step"\nstart = 0.5\namplitude = 0.2\n'
                  '[params]\nM = 0.55\n')
    assert main(["simulate", "--scenario", str(sc), "--csv", str(tmp_path / "a.csv")]) == 0
    assert main(["simulate", "--scenario", str(sc), "--csv", str(tmp_path / "b.csv"), "--plant", str(soft)]) == 0
    err = capsys.readouterr().err
    assert PRECEDENCE in err and "cart.M" in err
    assert (tmp_path / "a.csv").read_text() != (tmp_path / "b.csv").read_text()
    # closed loop around a continuous design, and open loop: the plant is the plant file's
    for mode in (["--design", "lqr"], ["--open-loop"]):
        assert main(["simulate", *mode, "--phi0", "0.05", "--duration", "0.5", "--csv", str(tmp_path / "c.csv")]) \
            in (0, 1)
        c = (tmp_path / "c.csv").read_text()
        main(["simulate", *mode, "--phi0", "0.05", "--duration", "0.5", "--csv", str(tmp_path / "d.csv"),
              "--plant", str(soft)])
        assert c != (tmp_path / "d.csv").read_text()


def test_simulate_refuses_a_plant_file_at_another_loop_rate(tmp_path: Path) -> None:
    p = load_params()
    text = DEFAULT_PATH.read_text()
    bad = tmp_path / "r.toml"
    bad.write_text(text.replace(f"rate = {int(p.rate)}", f"rate = {2 * int(p.rate)}"))
    if load_params(bad).rate == p.rate:
        pytest.skip("robot.toml spells the rate differently")
    assert main(["simulate", "--scenario", "tilt_0p1", "--csv", str(tmp_path / "x.csv"), "--plant", str(bad)]) == 2


def test_sweep_accepts_plant(soft: Path, tmp_path: Path) -> None:
    common = ["sweep", "robustness", "--n", "6", "--seed", "3", "--duration", "1.0", "--quiet", "--no-plots",
              "--worst", "0"]
    assert main([*common, "--out", str(tmp_path / "a")]) in (0, 1)
    assert main([*common, "--out", str(tmp_path / "b"), "--plant", str(soft)]) in (0, 1)
    a = (tmp_path / "a" / "robustness.csv").read_text()
    b = (tmp_path / "b" / "robustness.csv").read_text()
    assert a != b
    assert main(["sweep", "tilt", "--step", "0.2", "--duration", "0.5", "--noise", "none", "--quiet", "--no-plots",
                 "--out", str(tmp_path / "t"), "--plant", str(soft)]) in (0, 1)


def test_sweep_centres_the_ranges_on_the_plant(soft: Path) -> None:
    from host.studies.sweep import SweepConfig, sample_runs

    p, plant = load_params(), load_params(soft)
    _, nom = sample_runs(SweepConfig(params=p, seed=1), 0, 50)
    _, off = sample_runs(SweepConfig(params=p, seed=1, plant=plant), 0, 50)
    assert math.isclose(float(np.mean(off["I"] / nom["I"])), 0.7, rel_tol=1e-9)


@pytest.mark.slow
def test_demo_accepts_plant(soft: Path, tmp_path: Path) -> None:
    r = _cli("demo", "--scenario", "tilt_0p1", "--no-design", "--no-gif", "--quiet", "--out", str(tmp_path),
             "--plant", str(soft))
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"plant: {soft}" in r.stderr and "tilt_0p1" in r.stdout


def test_plant_by_name_from_sim_plants(tmp_path: Path, capsys) -> None:
    # the README's example: a bare name is looked up in sim/plants/
    assert main(["simulate", "--scenario", "tilt_0p1", "--csv", str(tmp_path / "x.csv"), "--plant", "soft_pendulum"]) == 0
    err = capsys.readouterr().err
    assert "plant: soft_pendulum" in err and "differs in: pendulum.I" in err
    assert math.isclose(load_params(ROOT / "sim" / "plants" / "soft_pendulum.toml").I, 0.7 * load_params().I)
