"""``upright sweep``: smoke tests with small N; the outputs load back."""

from __future__ import annotations

import csv

import numpy as np
import pyarrow.parquet as pq
import pytest

from host.cli import main as cli
from host.cli.sweep import parse_noise
from host.design.discrete import Q_DEFAULT
from sim.scenario import load_scenario


@pytest.mark.slow  # 3-5 s on the loaded 2-core machine: out of the fast loop
def test_robustness_writes_tables_plots_and_replayable_scenarios(tmp_path, capsys) -> None:
    out = tmp_path / "rob"
    rc = cli.main(["sweep", "robustness", "--n", "6", "--chunk", "4", "--seed", "5", "--duration", "1.0",
                   "--worst", "2", "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr()
    assert "success" in text.out and "6/6 runs" in text.err
    rows = list(csv.DictReader((out / "robustness.csv").open()))
    assert len(rows) == 6 and [int(r["run"]) for r in rows] == list(range(6))
    t = pq.read_table(out / "robustness.parquet").to_pydict()
    assert t["run"] == list(range(6))
    assert [float(r["phi_max"]) for r in rows] == pytest.approx(t["phi_max"], rel=0, abs=0)
    assert (out / "robustness.png").stat().st_size > 1000
    scen = sorted((out / "scenarios").glob("*.toml"))
    assert len(scen) == 2
    s = load_scenario(scen[0])
    assert s.duration == 1.0 and s.noise.kind == "uniform" and s.delay is not None


def test_tune_and_tilt_smoke(tmp_path, capsys) -> None:
    assert cli.main(["sweep", "tune", "--search", "random", "--designs", "2", "--n", "2", "--duration", "0.5",
                     "--quiet", "--no-plots", "--out", str(tmp_path)]) == 0
    assert "Pareto front" in capsys.readouterr().out
    d = pq.read_table(tmp_path / "tune_designs.parquet").to_pydict()
    assert len(d["design"]) == 2
    assert cli.main(["sweep", "tilt", "--step", "0.2", "--duration", "0.5", "--noise", "none", "--quiet",
                     "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "atan(a_max/g) = 0.4718 rad" in out
    assert (tmp_path / "tilt.png").exists() and (tmp_path / "tilt.csv").exists()


def test_bad_arguments_are_clear_errors(tmp_path, capsys) -> None:
    assert cli.main(["sweep", "robustness", "--noise", "pink:1", "--out", str(tmp_path)]) == 2
    assert "--noise" in capsys.readouterr().err
    assert cli.main(["sweep", "robustness", "--duration", "-1", "--out", str(tmp_path)]) == 2
    assert cli.main(["sweep", "robustness", "--r", "-1", "--quiet", "--out", str(tmp_path)]) == 2
    assert "R > 0" in capsys.readouterr().err
    assert cli.main(["sweep", "robustness", "--observer", "0", "--quiet", "--out", str(tmp_path)]) == 2
    with pytest.raises(SystemExit):
        cli.main(["sweep", "robustness", "--n", "0"])
    with pytest.raises(SystemExit):
        cli.main(["sweep", "wobble"])


def test_a_chosen_design_is_swept(tmp_path, capsys) -> None:
    assert cli.main(["sweep", "robustness", "--n", "3", "--duration", "0.4", "--q-x", "1", "--r", "0.1",
                     "--observer", "0.5", "--worst", "1", "--quiet", "--no-plots", "--out", str(tmp_path)]) == 0
    capsys.readouterr()
    s = load_scenario(next((tmp_path / "scenarios").glob("*.toml")))
    assert f"design qx1_qphi{Q_DEFAULT[2]:g}_r0.1_obs0.5" in s.expect.note  # q_phi not given: the shipped one


def test_parse_noise() -> None:
    assert parse_noise("none").kind == "none"
    assert parse_noise("uniform:0.005").amplitude == 0.005
    assert parse_noise("white:1e-5").power == 1e-5
    for bad in ("white", "uniform:x", "none:1", "white:-1"):
        with pytest.raises(ValueError):
            parse_noise(bad)
    assert np.isclose(parse_noise("white:1e-5").std(0.002), np.sqrt(1e-5 / 0.002))
