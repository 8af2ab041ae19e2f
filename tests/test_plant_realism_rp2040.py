"""Plant realism on the emulated RP2040 (issue 24 item 1): ``upright hil --emulate rp2040 --plant``
runs the board's own firmware against the realistic cart through the same PlantSim, no code of
its own (the counts on the pins are the realistic plant's)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from host.boards.rp2040.board import ROOT

from test_plant_realism import REALISTIC, SHORT, SHORT_TOML, replay_matches

pytestmark = pytest.mark.rp2040  # slow; skipped without the emulated board (tests/conftest.py)


def test_hil_emulated_rp2040_runs_the_realistic_plant(tmp_path: Path) -> None:
    sc = tmp_path / "short_tilt.toml"
    sc.write_text(SHORT_TOML)
    out = tmp_path / "emu"
    r = subprocess.run([sys.executable, "-m", "host.cli.main", "hil", "--emulate", "rp2040", "--plant", str(REALISTIC),
                        "--scenario", str(sc), "--out", str(out), "--no-plots", "--no-compare", "--quiet"],
                       cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode in (0, 1), r.stdout + r.stderr
    assert "differs in: cart.coulomb" in r.stderr
    replay_matches(out / "short_tilt.csv", SHORT)
