"""Robust design in HIL (issue 15 item 2): the shipped default, firmware in the loop, on plants at
corners of the uncertainty set (``upright hil --plant``), passes the report's scenarios where the
robust evaluation says it does, and fails where it says it fails.

* The MicroPython unix port (``hal_hil``) has no supply divider: its duty assumes the nominal
  supply, so it is compared with the evaluation with ``supply_measured = false``.
* The emulated RP2040 runs ``main.py`` with ``HalPico``, which measures the motor supply on its
  divider's pin (``firmware/board.py`` ``VSUP_ADC_PIN``) and scales the duty by it; the HIL puts
  the simulated robot's supply on that pin.  With the supply 15 % low (the face of the box; the
  rest nominal) the board settles the 0.1 rad tilt within every limit, as the evaluation with the
  supply measured says -- and the unix port, without the divider, does not (4.6 s), which is
  what the measurement buys.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from host.design import robust as R
from sim.params import load_params

ROOT = Path(__file__).resolve().parents[1]

# two vertices of sim/uncertainty.toml (delay in ms)
CORNERS = {
    "heavy_strong_drive": ({"inertia": 1.2, "cart_mass": 1.2, "pendulum_mass": 1.2, "friction": 0.5, "supply": 1.15,
                            "motor_constant": 1.1}, 20),
    "light_weak_drive": ({"inertia": 0.5, "cart_mass": 0.8, "pendulum_mass": 0.8, "friction": 0.5, "supply": 0.85,
                          "motor_constant": 0.9}, 20),
}
HIL_SCENARIO = {"step": "ref_step_20cm", "square": "square_wave_20cm_2p2s", "tilt": "tilt_0p1", "push": "push_0p2N_5s",
                "kick": "impulse_kick"}


def _corner(name: str) -> R.Point:
    params = load_params(None)
    factors, delay_ms = CORNERS[name]
    return R.Point({**{k: 1.0 for k in R.FACTORS}, **factors}, round(delay_ms * 1e-3 * params.rate), True)


def _evaluate(point: R.Point, supply_measured: bool) -> R.Evaluation:
    params = load_params(None)
    uset = dataclasses.replace(R.load_uncertainty(), supply_measured=supply_measured)
    return R.evaluate(params, R.shipped(), uset, points=[point], push=True)


def _verdicts(ev: R.Evaluation) -> dict[str, bool]:
    """Scenario -> every constraint met at the (single) point (the kick's acceleration is none)."""
    return {s: all(not ev.ratios(s, c)[0] > 1.0 for c in R.CONSTRAINTS) for s in R.SCENARIOS}


def _hil(tmp_path: Path, point: R.Point, scenarios: list[str], *extra: str) -> list[dict]:
    params = load_params(None)
    tmp_path.mkdir(parents=True, exist_ok=True)
    plant = tmp_path / "corner.toml"
    plant.write_text(R.plant_toml(point, params))
    out = tmp_path / "hil.json"
    r = subprocess.run([sys.executable, "-m", "host.cli", "hil", *extra, "--scenario", ",".join(scenarios),
                        "--plant", str(plant), "--json", str(out), "--no-plots", "--no-compare", "--quiet",
                        "--out", str(tmp_path / "o")], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert r.returncode in (0, 1), r.stderr
    return json.loads(out.read_text())


def _met(run: dict) -> bool:
    return all(v["status"] == "PASS" for c, v in run["checks"].items() if c != "a_max" or run["name"] != "impulse_kick")


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CORNERS))
def test_unix_port_hil_at_a_corner_agrees_with_the_evaluation(tmp_path: Path, name: str) -> None:
    point = _corner(name)
    ev = _evaluate(point, supply_measured=False)
    want = _verdicts(ev)
    if name == "heavy_strong_drive":  # where the shipped design meets every scenario without the divider
        assert all(want.values()), want
    else:  # the weak drive without the divider: the tilt is not settled in time
        assert not want["tilt"], want
    runs = {r["name"]: r for r in _hil(tmp_path, point, list(HIL_SCENARIO.values()))}
    for s, sc in HIL_SCENARIO.items():
        assert _met(runs[sc]) is want[s], (s, runs[sc]["checks"], {c: ev.metrics[s][c][0] for c in R.CONSTRAINTS})
    # the figures of the tilt, the one scenario both define alike (released at rest, 5 s)
    tilt = runs["tilt_0p1"]
    assert tilt["accel_max"] == pytest.approx(ev.metrics["tilt"]["a_max"][0], rel=0.05)
    assert tilt["phi_max"] == pytest.approx(ev.metrics["tilt"]["phi_max"][0], abs=0.003)


@pytest.mark.rp2040
@pytest.mark.skipif(shutil.which("node") is None, reason="node not installed")
def test_emulated_board_measures_its_supply_and_settles_a_low_supply_robot(tmp_path: Path) -> None:
    from host.boards.rp2040.board import FIRMWARE

    if not FIRMWARE.is_file() or not (ROOT / "node_modules" / "rp2040js").is_dir():
        pytest.skip("MicroPython RP2040 image or rp2040js missing (make rp2040)")
    params = load_params(None)
    point = R.Point({**{k: 1.0 for k in R.FACTORS}, "supply": 0.85}, round(params.delay * params.rate), False)
    ev = _evaluate(point, supply_measured=True)
    assert _verdicts(ev)["tilt"]  # the supply measured: the tilt passes here ...
    ev_n = _evaluate(point, supply_measured=False)
    assert not _verdicts(ev_n)["tilt"]  # ... and without the divider it does not (settled too late)
    (run,) = _hil(tmp_path / "board", point, ["tilt_0p1"], "--emulate", "rp2040")
    assert run["passed"] is True and _met(run), run["checks"]
    assert run["settle_s"] is not None and run["settle_s"] <= params.t_settle
    assert run["accel_max"] == pytest.approx(ev.metrics["tilt"]["a_max"][0], rel=0.05)
    assert run["phi_max"] == pytest.approx(ev.metrics["tilt"]["phi_max"][0], abs=0.003)
    # the same robot on the unix port (no divider): the settling the evaluation predicts, too late
    (unix,) = _hil(tmp_path / "unix", point, ["tilt_0p1"])
    assert not _met(unix) and unix["settle_s"] is not None and unix["settle_s"] > params.t_settle
    assert unix["settle_s"] == pytest.approx(ev_n.metrics["tilt"]["settle"][0], abs=0.3)
