"""``upright sweep hil``: the HIL Monte Carlo (firmware in the loop, one MicroPython board per worker).

Runs ``--n`` perturbed robots (the ``--ranges``, drawn as the batch robustness sweep draws them:
same ``--seed``, same run index, same robot) through ``--scenario`` on the virtual board -- in this
process, on a local Dask cluster of ``--workers`` processes, or on the cluster at ``--scheduler``
(workers with one thread each).  Writes ``hil_mc.csv``/``.parquet`` and ``hil_summary.json``;
Ctrl-C writes the runs that finished (marked partial) and exits 130.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from host.cli import args as A

__all__ = ["run_hil_mc"]


def run_hil_mc(args: argparse.Namespace, params: Any, unc: Any, out: Path, bar: Any,
               write_table: Callable[[Any, Path], list[Path]], fmt_table: Callable[..., str]) -> int:
    """Run the HIL Monte Carlo and print/write its table (``write_table``, ``fmt_table``: the sweep
    command's writers, passed in so this module does not import it back)."""
    from host.hil.runs import resolve_scenarios
    from host.studies.hil_mc import HilMcConfig, close_session, hil_tasks, run_hil_task
    from host.studies.sweep import concat, run_tasks
    from sim.scenario import ScenarioError

    if getattr(args, "plant", None) is not None:
        raise A.UsageError("--plant does not apply to sweep hil (each run draws its own robot around --params)")
    if args.workers is not None and args.scheduler is not None:
        raise A.UsageError("give --workers (a local cluster) or --scheduler, not both")
    try:
        scenarios = resolve_scenarios(args.scenario)
    except (ScenarioError, ValueError, OSError) as exc:
        raise A.UsageError(f"--scenario: {exc}") from None
    if len(scenarios) != 1:
        raise A.UsageError(f"--scenario: give one scenario, got {len(scenarios)}")
    n = args.n or 8
    cfg = HilMcConfig(params, scenarios[0], unc, args.seed)
    tasks = hil_tasks(cfg, n, 1)
    cluster: Any = None
    client: Any = None
    scheduler: Any = args.scheduler
    if args.workers is not None:
        from distributed import Client, LocalCluster

        cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=None)
        client = Client(cluster)
        scheduler = client
    print(f"HIL Monte Carlo: {n} runs of {scenarios[0].name} through the firmware (MicroPython unix port), "
          + (f"{args.workers} local Dask workers" if args.workers else "on Dask" if args.scheduler else "in this process"))
    t0 = time.perf_counter()
    try:
        table = concat(run_tasks(tasks, scheduler=scheduler, progress=bar, fn=run_hil_task))
    finally:
        close_session()
        if client is not None:
            try:
                client.run(close_session)  # each worker's board, before the cluster goes
            except Exception:  # noqa: BLE001 - a worker already gone has no board left
                pass
            client.close()
        if cluster is not None:
            cluster.close()
    wall = time.perf_counter() - t0
    passed = np.asarray(table["passed"], dtype=bool)
    summary = {"runs": n, "seed": args.seed, "scenario": scenarios[0].name, "wall_s": wall,
               "passed_rate": float(np.mean(passed)), "workers": int(len(set(table["worker"].tolist()))),
               "phi_max_max": float(np.max(table["phi_max"])), "xddot_max_max": float(np.max(table["xddot_max"])),
               "settle_max": float(np.max(table["settle"]))}
    print(f"{n} runs in {wall:.1f} s on {summary['workers']} board process(es): passed {np.mean(passed):.0%}")
    order = np.argsort(-np.asarray(table["phi_max"]), kind="stable")[:5]
    rows = [{k: (float(table[k][i]) if k != "run" else int(table[k][i])) for k in
             ("run", "delay", "I", "b", "phi_max", "settle", "xddot_max")} | {"passed": bool(passed[i])} for i in order]
    print(fmt_table(rows, ("run", "delay", "I", "b", "phi_max", "settle", "xddot_max", "passed")))
    files = write_table(table, out / "hil_mc")
    path = out / "hil_summary.json"
    path.write_text(json.dumps(summary, indent=2))
    files.append(path)
    print("wrote " + ", ".join(str(f) for f in files))
    return 0
