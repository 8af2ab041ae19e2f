"""``upright design`` prints the report and writes its figures."""

from __future__ import annotations

from pathlib import Path

import pytest

from host.cli.main import main


@pytest.mark.slow
def test_design_report_and_figures(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["design", "--no-search", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    for needle in ("det Wr = 12453", "Critical gain of (s+1)^2/s: 3.6", "-47.74", "20 (s+1)(s+10)/s", "CS:UNSTABLE"):
        assert needle in text
    for name in ("pole_zero", "responses", "nyquist", "gang_of_four"):
        png = tmp_path / f"{name}.png"
        assert png.read_bytes()[:4] == b"\x89PNG" and png.stat().st_size > 10_000


def test_report_seed_json(capsys: pytest.CaptureFixture[str]) -> None:
    import json

    assert main(["report", "seed", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    for key in ("eigenvalues", "tf_phi_num", "tf_phi_den", "det_wr", "rank_wo", "zeta", "omega", "k_place", "k_lqr", "critical_gain"):
        assert key in data
    assert data["tf_phi_den"][0] == 1.0


def test_report_seed_table(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["report", "seed"]) == 0
    out = capsys.readouterr().out
    assert "k_lqr" in out and "deviation" in out
