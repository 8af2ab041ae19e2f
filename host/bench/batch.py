"""Benchmark: the vectorised batch closed loop against python-control, run by run.

10,000 closed-loop runs of 5 s (robustness-sweep robots: masses, inertia, friction,
motor constants, delay 5-20 ms, noise, initial tilt), the plant integrated with RK4 at
1 kHz and the discrete controller at the loop rate, are simulated

* by :func:`sim.batch.simulate_batch` in one process (numpy over the batch axis),
* the same, split into two halves on two worker processes (the machine's 2 cores),
* run by run with python-control's ``input_output_response`` of the same closed loop
  (:func:`sim.batch.simulate_run`) -- too slow to do 10,000 times, so a sample of runs
  is timed and the time extrapolated to 10,000 runs.

The claim is the ratio of the per-run time to the batch time, both on one core; the
sample's trajectories are also compared with the batch's (max deviation in the notes).
"""

from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from typing import Any

import numpy as np

__all__ = ["bench", "N_RUNS", "DURATION", "SAMPLE"]

N_RUNS = 10_000
DURATION = 5.0
SAMPLE = 8  # runs simulated one by one with python-control


def _config() -> Any:
    from sim.params import load_params
    from host.studies.sweep import SweepConfig

    return SweepConfig(params=load_params(), seed=2026, duration=DURATION)


def _half(start: int, stop: int) -> float:
    from sim.batch import simulate_batch
    from host.studies.sweep import sample_runs

    cfg = _config()
    runs, _ = sample_runs(cfg, start, stop)
    ctrl = cfg.design.controller(cfg.params)
    t0 = time.perf_counter()
    simulate_batch(cfg.params, ctrl, runs, duration=cfg.duration, noise=cfg.noise)
    return time.perf_counter() - t0


def bench() -> dict[str, Any]:
    """Time the batch simulator (1 and 2 processes) and python-control run by run."""
    from sim.batch import simulate_batch, simulate_run
    from host.studies.sweep import sample_runs

    cfg = _config()
    p = cfg.params
    ctrl = cfg.design.controller(p)
    t0 = time.perf_counter()
    runs, _ = sample_runs(cfg, 0, N_RUNS)
    t_sample = time.perf_counter() - t0

    t0 = time.perf_counter()
    res = simulate_batch(p, ctrl, runs, duration=DURATION, noise=cfg.noise)
    t_batch = time.perf_counter() - t0

    half = N_RUNS // 2
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=2, mp_context=get_context("spawn")) as ex:
        parts = list(ex.map(_half, (0, half), (half, N_RUNS)))
    t_two = time.perf_counter() - t0

    sample = runs.subset(slice(0, SAMPLE))
    t0 = time.perf_counter()
    ref = [simulate_run(p, ctrl, sample, i, duration=DURATION, noise=cfg.noise) for i in range(SAMPLE)]
    t_ct = time.perf_counter() - t0
    per_run = t_ct / SAMPLE
    t_ct_all = per_run * N_RUNS
    rec = simulate_batch(p, ctrl, sample, duration=DURATION, noise=cfg.noise, record=True).traces
    assert rec is not None
    dev = max(float(np.max(np.abs(ref[i][k] - rec[k][:, i]))) for i in range(SAMPLE) for k in ("x", "xdot", "phi", "phidot"))
    ticks = int(round(DURATION / ctrl.Ts))
    rows = [
        {"variant": "batch (numpy), 1 process", "runs": N_RUNS, "wall_s": t_batch, "runs_per_s": N_RUNS / t_batch,
         "vs_python_control": t_ct_all / t_batch},
        {"variant": "batch (numpy), 2 processes", "runs": N_RUNS, "wall_s": t_two, "runs_per_s": N_RUNS / t_two,
         "vs_python_control": t_ct_all / t_two},
        {"variant": f"python-control input_output_response, run by run ({SAMPLE} timed, extrapolated)", "runs": N_RUNS,
         "wall_s": t_ct_all, "runs_per_s": 1.0 / per_run, "vs_python_control": 1.0},
    ]
    ok = float(np.mean(~res.metrics["fallen"]))
    notes = [
        f"{N_RUNS} runs x {DURATION:g} s: controller at {1 / ctrl.Ts:g} Hz ({ticks} ticks), plant RK4 at 1 kHz "
        f"(2 sub-steps per tick), motor model, 12-bit ADC and encoder quantisation, uniform noise, delay 5-20 ms.",
        f"goal: under 60 s on 2 cores -> {t_two:.1f} s with 2 processes (end to end: spawn, sampling, simulation; "
        f"simulation alone {max(parts):.1f} s), {t_batch:.1f} s in one process.",
        f"python-control: {SAMPLE} runs timed ({t_ct:.1f} s, {per_run:.2f} s per run) and EXTRAPOLATED to {N_RUNS} runs "
        f"({t_ct_all:.0f} s); ratio 1 process vs 1 process = {t_ct_all / t_batch:.0f}x (goal >= 100x).",
        f"the {SAMPLE} sampled runs agree with the batch to {dev:.1e} (max |state difference| over all ticks).",
        f"drawing the {N_RUNS} robots and seeds (not timed above): {t_sample:.1f} s; {ok:.1%} of the runs stayed upright.",
    ]
    return {"title": "Batch closed-loop simulation: numpy batch vs python-control run by run", "rows": rows, "notes": notes}
