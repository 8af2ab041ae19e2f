"""``upright simulate --scenario``: the float closed loop of a scenario, CSV, summary, plot."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from host.cli.main import main


def test_scenario_run_writes_csv_summary_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, png = tmp_path / "tilt.csv", tmp_path / "tilt.png"
    assert main(["simulate", "--scenario", "tilt_0p1", "--csv", str(out), "--plot", str(png)]) == 0
    rows = list(csv.DictReader(out.open()))
    assert list(rows[0]) == ["t", "x", "xdot", "phi", "phidot", "force"]
    phi = np.array([float(r["phi"]) for r in rows])
    assert abs(phi[0]) == pytest.approx(0.1) and np.max(np.abs(phi[-100:])) < 0.01  # balanced
    assert "tilt_0p1" in capsys.readouterr().err
    assert png.stat().st_size > 10_000


def test_unknown_scenario_is_a_one_line_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", "--scenario", "no_such_scenario"]) != 0
    err = capsys.readouterr().err.strip()
    assert "no_such_scenario" in err and "\n" not in err
