"""Scale-out: sweeps on a Dask LocalCluster (loopback) equal the single-process results."""

from __future__ import annotations

import numpy as np
import pytest

from host.studies.dask_run import DaskRunError, run_on_dask
from sim.params import load_params
from host.studies.sweep import Design, SweepConfig, robustness, run_task, tasks_for, tilt, tune

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp",
                                  host="127.0.0.1", dashboard_address=None) as lc:
        yield lc


@pytest.fixture(scope="module")
def cfg():
    return SweepConfig(params=load_params(), seed=11, duration=0.4)


def test_robustness_on_dask_equals_single_process(cluster, cfg) -> None:
    local = robustness(cfg, 10, chunk=10)
    seen = []
    remote = robustness(cfg, 10, chunk=3, scheduler=cluster.scheduler_address, progress=lambda d, t: seen.append((d, t)))
    assert set(local) == set(remote)
    for k in local:
        assert np.array_equal(local[k], remote[k]), k
    assert seen[0] == (0, 10) and seen[-1] == (10, 10)


@pytest.mark.slow
def test_tune_and_tilt_on_dask_equal_single_process(cluster, cfg) -> None:
    designs = [Design("soft", R=0.1), Design("report")]
    rows_l, t_l = tune(cfg, designs, 3, chunk=2)
    rows_r, t_r = tune(cfg, designs, 3, chunk=2, scheduler=cluster.scheduler_address)
    assert rows_l == rows_r
    assert all(np.array_equal(t_l[k], t_r[k]) for k in t_l)
    p = cfg.params
    a, _ = tilt(p, designs, step=0.15, hi=0.3, duration=0.4)
    b, _ = tilt(p, designs, step=0.15, hi=0.3, duration=0.4, scheduler=cluster.scheduler_address)
    assert a == b


def test_client_object_and_task_errors(cluster, cfg) -> None:
    with distributed.Client(cluster.scheduler_address) as client:
        tables = run_on_dask(tasks_for(cfg, 2, 1), client, run_task)
        assert [int(t["run"][0]) for t in tables] == [0, 1]
        bad = SweepConfig(params=cfg.params, design=Design(observer=-1.0), duration=0.1)
        with pytest.raises(DaskRunError, match="runs 0..1"):
            run_on_dask(tasks_for(bad, 1), client, run_task)


def test_unreachable_scheduler_is_a_clear_error(cfg) -> None:
    with pytest.raises(DaskRunError, match="cannot reach"):
        run_on_dask(tasks_for(cfg, 1), "tcp://127.0.0.1:9", run_task, timeout=1.0)


def test_cli_with_scheduler_writes_the_same_table(cluster, tmp_path) -> None:
    import pyarrow.parquet as pq

    from host.cli import main as cli

    common = ["sweep", "robustness", "--n", "5", "--chunk", "2", "--duration", "0.5", "--seed", "4", "--quiet", "--no-plots"]
    assert cli.main([*common, "--out", str(tmp_path / "local")]) == 0
    assert cli.main([*common, "--scheduler", cluster.scheduler_address, "--out", str(tmp_path / "dask")]) == 0
    a = pq.read_table(tmp_path / "local" / "robustness.parquet")
    b = pq.read_table(tmp_path / "dask" / "robustness.parquet")
    assert a.equals(b)
    assert (tmp_path / "local" / "robustness.csv").read_text() == (tmp_path / "dask" / "robustness.csv").read_text()
