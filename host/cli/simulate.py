"""``upright simulate``: integrate the nonlinear plant, open loop or closed around a design.

Writes a CSV with columns ``t,x,xdot,phi,phidot,force`` (SI units; ``force`` is the total
force applied at the cart: controller output plus the disturbance profile).

Examples
--------
The pendulum falling from 0.05 rad with no force::

    upright simulate --open-loop --phi0 0.05 --duration 0.6 --csv out.csv

The report's LQR design holding a 0.2 N push for 5 s::

    upright simulate --design lqr --push 0.2 --push-duration 5 --duration 8 --csv lqr.csv

A scenario (``sim/scenarios/*.toml`` or a path) with the discrete controller the firmware
runs, in float, through the motor, sensor, delay and noise models; with a summary and plot::

    upright simulate --scenario ref_step_20cm --csv step.csv --plot step.png
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path
from typing import Callable

import numpy as np

from sim.params import load_params
from sim.plant import simulate

DESIGNS = ("place", "lqr", "place-observer", "lqr-observer", "pid", "loopshape")


def write_csv(path: str | Path, res: dict[str, np.ndarray]) -> None:
    """Write a simulation result as CSV (``-`` for stdout)."""
    cols = ("t", "x", "xdot", "phi", "phidot", "force")
    fh = sys.stdout if str(path) == "-" else open(path, "w", newline="")
    try:
        w = csv.writer(fh)
        w.writerow(cols)
        for row in zip(*(res[c] for c in cols)):
            w.writerow([f"{v:.10g}" for v in row])
    finally:
        if fh is not sys.stdout:
            fh.close()


def push_profile(amplitude: float, start: float, duration: float) -> Callable[[float], float]:
    """A constant push of ``amplitude`` N from ``start`` for ``duration`` s."""
    return lambda t: amplitude if start <= t < start + duration else 0.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright simulate``."""
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--open-loop", action="store_true", help="no controller: only the force profile acts")
    mode.add_argument("--design", choices=DESIGNS, help="close the loop around this design (continuous-time, sampled at --dt)")
    mode.add_argument(
        "--scenario",
        metavar="NAME",
        help="run a scenario (name in sim/scenarios or a TOML path) with the firmware's discrete controller in float",
    )
    parser.add_argument("--params", metavar="TOML", help="parameter file (default: the report's robot)")
    parser.add_argument("--x0", type=float, default=0.0, help="initial cart position (m)")
    parser.add_argument("--phi0", type=float, default=0.0, help="initial tilt from upright (rad)")
    parser.add_argument("--reference", type=float, default=0.0, help="cart position reference (m) for state feedback")
    parser.add_argument("--push", type=float, default=0.0, help="disturbance force (N)")
    parser.add_argument("--push-start", type=float, default=0.0, help="when the push starts (s)")
    parser.add_argument("--push-duration", type=float, default=5.0, help="how long the push lasts (s)")
    parser.add_argument("--duration", type=float, default=5.0, help="simulated time (s)")
    parser.add_argument("--dt", type=float, default=1e-3, help="log and controller sample period (s)")
    parser.add_argument("--substeps", type=int, default=4, help="RK4 steps per sample")
    parser.add_argument("--u-limit", type=float, default=None, help="saturate the controller force (N)")
    parser.add_argument("--csv", default="-", help="output CSV path ('-' for stdout, the default)")
    parser.add_argument("--plot", metavar="PNG", help="with --scenario: write the run's plot here")


def run_scenario(args: argparse.Namespace) -> int:
    """``--scenario``: the float closed loop of a scenario, CSV + summary (+ plot)."""
    from host.design.discrete import controller_for
    from sim.metrics import evaluate, summary_table
    from sim.plantsim import run_scenario_float
    from sim.scenario import load_scenario

    params = load_params(args.params)
    scenario = load_scenario(args.scenario)
    log = run_scenario_float(scenario, params, controller_for(scenario, params), init="measured")
    write_csv(args.csv, {"force": log["force"], **{k: log[k] for k in ("t", "x", "xdot", "phi", "phidot")}})
    summary = evaluate(log, scenario, params, name=scenario.name)
    print(summary_table([summary], title="Float simulation of the firmware's discrete controller"), file=sys.stderr)
    if args.plot:
        from sim.plots import plot_run

        plot_run(log, args.plot, params, title=f"{scenario.name}: float simulation", metrics=summary.metrics)
        print(f"plot: {args.plot}", file=sys.stderr)
    return 0


def run(args: argparse.Namespace) -> int:
    """Run the simulation and write the CSV."""
    if args.scenario:
        return run_scenario(args)
    params = load_params(args.params)
    if args.duration <= 0 or args.dt <= 0 or args.substeps < 1:
        raise ValueError("--duration, --dt and --substeps must be positive")
    controller = None
    if args.design:
        from host.design.controllers import make_controller

        controller = make_controller(params, args.design, reference=args.reference, dt=args.dt)
    force = push_profile(args.push, args.push_start, args.push_duration) if args.push else None
    res = simulate(
        params,
        [args.x0, 0.0, args.phi0, 0.0],
        args.duration,
        force=force,
        controller=controller,
        dt=args.dt,
        substeps=args.substeps,
        u_limit=args.u_limit,
    )
    write_csv(args.csv, res)
    if args.csv != "-":
        print(
            f"wrote {args.csv}: {len(res['t'])} samples, final phi {res['phi'][-1]:+.4f} rad, "
            f"peak |phi| {np.max(np.abs(res['phi'])):.4f} rad, final x {res['x'][-1]:+.4f} m",
            file=sys.stderr,
        )
    return 0
