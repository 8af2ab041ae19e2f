"""The HIL run record: the firmware-vs-float comparison stops where the supervisor takes over,
and the HIL room's modules share the one loop through public names only."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np

from firmware.supervisor import ARMED, BALANCING, DISARMED, FAULT
from host.hil.results import HilRun, driven_ticks
from sim.params import load_params
from sim.scenario import scenario_from_dict

ROOT = Path(__file__).resolve().parent.parent
P = load_params()


def _run(state: list[int], phi: list[float], ref: list[float]) -> HilRun:
    sc = scenario_from_dict({"name": "synthetic", "duration": len(phi) / P.rate})
    log = {"phi": np.asarray(phi), "fw_state": np.asarray(state, dtype=np.int64)}
    return HilRun(sc, P, log, "lockstep", "serial", 1.0, reference={"phi": np.asarray(ref)})


def test_driven_ticks_end_at_fault_or_disarm() -> None:
    assert driven_ticks({"phi": np.zeros(5), "fw_state": np.array([BALANCING] * 5)}) == 5
    assert driven_ticks({"phi": np.zeros(5), "fw_state": np.array([BALANCING, BALANCING, FAULT, FAULT, FAULT])}) == 2
    assert driven_ticks({"phi": np.zeros(4), "fw_state": np.array([BALANCING, DISARMED, BALANCING, BALANCING])}) == 1
    # real time: a late first answer leaves the tick's state unknown (0); driving starts later
    assert driven_ticks({"phi": np.zeros(4), "fw_state": np.array([DISARMED, BALANCING, BALANCING, ARMED])}) == 3
    assert driven_ticks({"phi": np.zeros(3)}) == 3  # no states: driven throughout


def test_phi_error_ignores_what_happens_after_the_supervisor_cut() -> None:
    # the float design (no supervisor) runs on after the cut; the firmware's motor is off
    run = _run([BALANCING, BALANCING, BALANCING, FAULT, FAULT], [0.1, 0.15, 0.19, 0.6, 1.2], [0.1, 0.15, 0.191, 0.4, 0.5])
    assert math.isclose(run.phi_error(), 0.001, abs_tol=1e-12)
    # catch mode (|phi| >= 0.2 rad) is not in the float reference: compared up to it, nan from the start
    caught = _run([BALANCING] * 4, [0.1, 0.12, 0.25, 0.1], [0.1, 0.121, 0.5, 1.0])
    assert math.isclose(caught.phi_error(), 0.001, abs_tol=1e-12)
    assert math.isnan(_run([BALANCING] * 2, [0.3, 0.2], [0.3, 0.5]).phi_error())
    disarmed = _run([BALANCING, BALANCING, DISARMED, DISARMED], [0.0, 0.0, 0.5, 1.0], [0.0, 0.002, 0.0, 0.0])
    assert math.isclose(disarmed.phi_error(), 0.002, abs_tol=1e-12)
    # while it drives, a difference counts
    drives = _run([BALANCING] * 3, [0.0, 0.0, 0.05], [0.0, 0.0, 0.0])
    assert math.isclose(drives.phi_error(), 0.05, abs_tol=1e-12)


def test_hil_modules_share_no_private_names() -> None:
    # the one lockstep loop and its helpers are reused through public names (soak.py once
    # imported session's _peek)
    bad = []
    for path in sorted((ROOT / "host" / "hil").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("host."):
                bad += [f"{path.name}: {node.module}.{a.name}" for a in node.names if a.name.startswith("_")]
    assert not bad, bad
