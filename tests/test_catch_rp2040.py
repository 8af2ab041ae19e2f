"""Catch mode on the emulated RP2040 (issue 15 item 3): the board's own main.py (HalPico, paced
loop, UART0 link) catches the report's 0.3 rad tilt through its pins.  The tracking row alone
lets this tilt fall (tests/test_catch.py), so a board that stays up ran the catch path and
its hand-back.  1.5 s of board time (the hand-back comes at ~1.1 s): ~15-25 s wall with boot.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from host.boards.rp2040.board import build_bundle
from host.hil.emulated import EmulatedHil
from sim.params import load_params
from sim.scenario import load_scenario

pytestmark = pytest.mark.rp2040  # slow; skipped without the emulated board (tests/conftest.py)


def test_board_catches_0p3_rad_through_its_pins(tmp_path: Path) -> None:
    bundle = build_bundle(tmp_path / "bundle")
    sc = dataclasses.replace(load_scenario("tilt_0p3"), duration=1.5)
    with EmulatedHil(bundle) as h:
        run = h.run(sc, load_params())
    log = run.log
    phi = np.asarray(log["phi"], dtype=float)
    assert len(phi) >= 700
    assert int(np.max(np.asarray(log["fw_faults"]))) == 0, "the board latched a fault"
    assert float(np.max(np.abs(log["xddot"]))) <= 5.0
    assert float(np.max(np.abs(phi))) < 0.31
    # upright and calm after the hand-back
    assert float(np.max(np.abs(phi[-100:]))) < 0.1
