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
import math
import sys
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from host.cli import args as A
from host.cli.args import RunFailed, UsageError

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
        metavar="NAME", type=A.nonempty,
        help="run a scenario (name in sim/scenarios or a TOML path) with the firmware's discrete controller in float",
    )
    parser.add_argument("--params", metavar="TOML", help="parameter file (default: the report's robot)")
    from host.cli.plant import add_plant_argument

    add_plant_argument(parser)
    parser.add_argument("--x0", type=A.finite, default=0.0, help="initial cart position (m, within the track)")
    parser.add_argument("--phi0", type=A.tilt, default=0.0, help="initial tilt from upright (rad, |phi0| < pi/2)")
    parser.add_argument("--reference", type=A.finite, default=0.0,
                        help="cart position reference (m, within the track) for state feedback")
    parser.add_argument("--push", type=A.finite, default=0.0, help="disturbance force (N)")
    parser.add_argument("--push-start", type=A.nonneg, default=0.0, help="when the push starts (s)")
    parser.add_argument("--push-duration", type=A.positive, default=5.0, help="how long the push lasts (s)")
    parser.add_argument("--duration", type=A.duration(), default=5.0,
                        help=f"simulated time (s, at most {A.MAX_DURATION_S:g})")
    parser.add_argument("--dt", type=A.in_range(0.0, 0.1, lo_open=True, unit="s"), default=1e-3,
                        help="log and controller sample period (s, at most 0.1)")
    parser.add_argument("--substeps", type=A.int_range(1, 1000), default=4, help="RK4 steps per sample")
    parser.add_argument("--u-limit", type=A.positive, default=None, help="saturate the controller force (N, > 0)")
    parser.add_argument("--csv", default="-", help="output CSV path ('-' for stdout, the default)")
    parser.add_argument("--plot", metavar="PNG", help="with --scenario: write the run's plot here")


MAX_SAMPLES = 10_000_000
"""Most samples a run may log (``duration / dt``): beyond it the CSV alone is gigabytes."""


def _check_outputs(args: argparse.Namespace) -> None:
    A.check_out_file(args.csv, "--csv")
    A.check_out_file(args.plot, "--plot")


def check_run(t: np.ndarray, phi: np.ndarray, states: Sequence[np.ndarray], *, fall_expected: bool) -> None:
    """Raise :class:`~host.cli.args.RunFailed` if a run diverged or fell when it should not have.

    Diverged: a state that is not finite.  Fell: ``|phi|`` beyond pi/2 (the pendulum lies on
    the cart) while ``fall_expected`` is false.
    """
    bad = ~np.all([np.isfinite(s) for s in states], axis=0)
    if np.any(bad):
        k = int(np.argmax(bad))
        raise RunFailed(f"the simulation diverged: the state is not finite from t = {t[k]:.4g} s "
                        f"(the output was written up to there)")
    if not fall_expected:
        over = np.abs(phi) > math.pi / 2
        if np.any(over):
            k = int(np.argmax(over))
            raise RunFailed(f"the pendulum fell: |phi| passed pi/2 at t = {t[k]:.4g} s with no fall expected "
                            f"(the output was written)")


def run_scenario(args: argparse.Namespace) -> int:
    """``--scenario``: the float closed loop of a scenario, CSV + summary (+ plot)."""
    from host.design.discrete import controller_for
    from sim.metrics import evaluate, summary_table
    from sim.plantsim import run_scenario_float
    from sim.scenario import load_scenario

    _check_outputs(args)
    from host.cli.plant import load_plant, print_precedence

    params = load_params(args.params)
    plant = load_plant(getattr(args, "plant", None), params)
    scenario = load_scenario(args.scenario)
    scenario.check(params if plant is None else plant)
    print_precedence([scenario], plant)
    with np.errstate(all="ignore"):
        log = run_scenario_float(scenario, params, controller_for(scenario, params), init="measured", plant=plant)
    write_csv(args.csv, {"force": log["force"], **{k: log[k] for k in ("t", "x", "xdot", "phi", "phidot")}})
    states = [log[k] for k in ("x", "xdot", "phi", "phidot")]
    if not all(np.all(np.isfinite(v)) for v in states):
        check_run(log["t"], log["phi"], states, fall_expected=True)
    summary = evaluate(log, scenario, params if plant is None else plant, name=scenario.name, model="float")
    print(summary_table([summary], title="Float simulation of the firmware's discrete controller"), file=sys.stderr)
    if args.plot:
        from sim.plots import plot_run

        plot_run(log, args.plot, params, title=f"{scenario.name}: float simulation", metrics=summary.metrics)
        print(f"plot: {args.plot}", file=sys.stderr)
    check_run(log["t"], log["phi"], states, fall_expected=scenario.expect.phi_max != "pass")
    return 0


def run(args: argparse.Namespace) -> int:
    """Run the simulation and write the CSV."""
    if args.scenario is not None:
        return run_scenario(args)
    _check_outputs(args)
    params = load_params(args.params)
    from host.cli.plant import load_plant

    plant = load_plant(getattr(args, "plant", None), params)
    if args.duration / args.dt > MAX_SAMPLES:
        raise UsageError(f"--duration {args.duration:g} s at --dt {args.dt:g} s is {args.duration / args.dt:.3g} samples "
                         f"(at most {MAX_SAMPLES:.0e}): raise --dt or shorten the run")
    for flag, v in (("--x0", args.x0), ("--reference", args.reference)):
        if not abs(v) < params.track:
            raise UsageError(f"{flag} {v:g} m lies outside the track (|x| < {params.track:g} m, loop.track)")
    controller = None
    if args.design:
        from host.design.controllers import make_controller

        controller = make_controller(params, args.design, reference=args.reference, dt=args.dt)
    force = push_profile(args.push, args.push_start, args.push_duration) if args.push else None
    with np.errstate(all="ignore"):
        res = simulate(params if plant is None else plant, [args.x0, 0.0, args.phi0, 0.0], args.duration, force=force,
                       controller=controller,
                       dt=args.dt, substeps=args.substeps, u_limit=args.u_limit)
    write_csv(args.csv, res)
    states = [res[k] for k in ("x", "xdot", "phi", "phidot")]
    if not all(np.all(np.isfinite(v)) for v in states):
        check_run(res["t"], res["phi"], states, fall_expected=True)
    if args.csv != "-":
        print(
            f"wrote {args.csv}: {len(res['t'])} samples, final phi {res['phi'][-1]:+.4f} rad, "
            f"peak |phi| {np.max(np.abs(res['phi'])):.4f} rad, final x {res['x'][-1]:+.4f} m",
            file=sys.stderr,
        )
    # open loop the pendulum is expected to fall; around a design it is not
    check_run(res["t"], res["phi"], states, fall_expected=args.open_loop)
    return 0
