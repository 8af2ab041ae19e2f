"""Studies at scale (issue 15 item 5): sweep ranges from a TOML file, the HIL Monte Carlo on Dask
(one MicroPython board per worker), and an interrupted HIL sweep that keeps what finished."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil
import pyarrow.parquet as pq
import pytest

from host.studies.ranges import RangesError, load_ranges
from host.studies.sweep import SweepConfig, sample_runs
from sim.params import load_params

ROOT = Path(__file__).resolve().parents[1]
SHORT = 'name = "tilt_short"\ndescription = "0.05 rad, 1 s"\nduration = 1.0\n[initial]\nphi = 0.05\n'


def _upright(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "host.cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


@pytest.mark.slow
def test_sweep_ranges_file_sets_the_draw(tmp_path: Path) -> None:
    ranges = tmp_path / "r.toml"
    ranges.write_text("inertia = 0.4\nmass = 0.0\nmotor = 0.0\nfriction = [1.0, 1.0]\ndelay = [0.0, 0.004]\n")
    out = tmp_path / "sw"
    r = _upright("sweep", "robustness", "--n", "40", "--duration", "0.5", "--ranges", str(ranges), "--no-plots",
                 "--quiet", "--worst", "0", "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert f"ranges from {ranges}" in r.stdout
    t = pq.read_table(out / "robustness.parquet").to_pydict()
    p = load_params(None)
    I = np.array(t["I"]) / p.I
    assert np.all((I >= 0.6 - 1e-9) & (I <= 1.4 + 1e-9))
    assert I.min() < 0.8 and I.max() > 1.2  # wider than the default +-10 %
    assert np.allclose(t["M"], p.M) and np.allclose(t["b"], p.b) and np.allclose(t["kt"], p.kt)
    assert set(np.round(np.array(t["delay"]) * p.rate).astype(int)) <= {0, 1, 2}


@pytest.mark.slow
@pytest.mark.parametrize("text, key", [
    ("inertai = 0.3\n", "inertai"),
    ("mass = 1.5\n", "mass"),
    ("friction = [2.0, 0.5]\n", "friction"),
    ("delay = 0.01\n", "delay"),
    ("tilt = \"big\"\n", "tilt"),
])
def test_bad_ranges_file_names_the_key(tmp_path: Path, text: str, key: str) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(RangesError) as ei:
        load_ranges(f)
    assert ei.value.key == key
    if key == "inertai":
        r = _upright("sweep", "robustness", "--ranges", str(f), "--out", str(tmp_path / "o"))
        assert r.returncode == 2 and "inertai" in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_hil_monte_carlo_on_dask_one_board_per_worker(tmp_path: Path) -> None:
    scen = tmp_path / "short.toml"
    scen.write_text(SHORT)
    out = tmp_path / "hil"
    r = _upright("sweep", "hil", "--n", "4", "--workers", "2", "--scenario", str(scen), "--seed", "7", "--quiet",
                 "--ranges", str(ROOT / "sim" / "sweep_ranges.toml"), "--out", str(out))
    assert r.returncode == 0, r.stderr
    t = pq.read_table(out / "hil_mc.parquet").to_pydict()
    assert t["run"] == [0, 1, 2, 3]
    assert len(set(t["worker"])) == 2  # both workers ran runs, each on its own board
    assert all(n == 500 for n in t["ticks"])  # 1 s at 500 Hz, closed through the firmware
    assert all(t["passed"]) and max(t["phi_max"]) < 0.06
    # the same robots as runs 0..3 of the batch sweep with that seed and those ranges
    from host.studies.ranges import load_ranges as lr

    cfg = SweepConfig(params=load_params(None), uncertainty=lr(ROOT / "sim" / "sweep_ranges.toml"), seed=7)
    _, drawn = sample_runs(cfg, 0, 4)
    for k in ("I", "b", "kt", "delay"):
        assert np.allclose(t[k], drawn[k]), k
    summary = json.loads((out / "hil_summary.json").read_text())
    assert summary["workers"] == 2 and summary["passed_rate"] == 1.0


@pytest.mark.slow
def test_hil_sweep_interrupted_keeps_the_finished_runs(tmp_path: Path) -> None:
    scen = tmp_path / "short.toml"
    scen.write_text(SHORT)
    out = tmp_path / "hil"
    err = tmp_path / "err.txt"
    proc = subprocess.Popen([sys.executable, "-m", "host.cli", "sweep", "hil", "--n", "500", "--scenario", str(scen),
                             "--out", str(out)], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err.open("w"),
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 180
        while re.search(r" [2-9]/500 runs", err.read_text()) is None:
            assert proc.poll() is None, err.read_text()
            assert time.monotonic() < deadline, err.read_text()
            time.sleep(0.05)
        children = psutil.Process(proc.pid).children(recursive=True)
        assert children  # the MicroPython board
        os.kill(proc.pid, signal.SIGINT)
        rc = proc.wait(60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    text = err.read_text()
    assert rc == 130, text
    assert "Traceback" not in text and "partial results" in text
    summary = json.loads((out / "hil_summary.json").read_text())
    assert summary["partial"] is True and summary["runs_planned"] == 500
    assert 2 <= summary["runs_done"] < 500
    t = pq.read_table(out / "hil_mc.parquet").to_pydict()
    assert t["run"] == list(range(summary["runs_done"]))
    time.sleep(0.5)
    alive = [c for c in children if c.is_running() and c.status() != psutil.STATUS_ZOMBIE]
    assert not alive, [c.cmdline() for c in alive]
