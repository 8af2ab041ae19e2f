"""``upright identify LOG... [--json FILE] [--out robot.toml]``: the robot's parameters from its logs.

The logs are what ``upright board excite`` records (CSV or Parquet): a balancing run
(``excite`` column 1) and a cart-only run (column 2, or the file given with ``--cart-only``:
pendulum removed or locked, PRBS open loop, then the coast-down).  Cart-only runs alone (or
``--cart-only`` without a file) give the first stage (:func:`host.studies.identify_cart.identify_cart`):
the drive (kt, ke), the friction, the delay and the board's latency -- the model a first design
balances with, before any balancing run.  ``--params`` is the robot
TOML the board runs (its masses weighed, the drive and sensor constants); the estimates
(pivot inertia, m*L, friction, kt, ke, delay, pot offset) print with 95 % intervals and go to
``--out`` as a complete robot TOML for ``upright design --params``.  Method and assumptions:
:mod:`host.studies.identify`.  Examples::

    upright identify bal.csv cart.csv --out robot_id.toml
    upright identify bal.parquet --cart-only cart.parquet --json id.json
    upright identify cart.csv --cart-only --params robot.toml --out stage1.toml

Exit status: 0 done; 2 a bad log (one line naming the file and column), file or option;
1 the fit failed.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from host.cli import args as A


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright identify``."""
    parser.add_argument("logs", nargs="*", metavar="LOG", help="logs of upright board excite (.csv / .parquet)")
    parser.add_argument("--cart-only", action="append", default=[], metavar="LOG", nargs="?", const="",
                        help="a cart-only run whose log has no excite column (repeatable); without LOG: the first "
                             "stage only (drive, friction, delay from the cart-only runs; no balancing run needed)")
    parser.add_argument("--params", default=None, metavar="TOML",
                        help="the robot file the board runs: masses, drive, sensors (default sim/robot.toml)")
    parser.add_argument("--out", default=None, metavar="TOML", help="write the identified robot file here")
    parser.add_argument("--json", default=None, metavar="FILE", help="write the estimates and intervals as JSON")
    parser.add_argument("--fc", type=A.in_range(1.0, 60.0, unit="Hz"), default=None,
                        help="low-pass of the balancing-run signals, Hz (default 10, lowered for the gear "
                             "play the cart-only run finds)")
    parser.add_argument("--max-delay", type=A.in_range(0.0, 0.1, unit="s"), default=0.03,
                        help="largest sensor delay searched, s (default 0.03)")
    parser.add_argument("--boot", type=A.int_range(0, 10000), default=100,
                        help="bootstrap resamples for the intervals (default 100; 0: none)")


def run(args: argparse.Namespace) -> int:
    """Run ``upright identify``."""
    from host.studies.identify import (PARAM_NAMES, STAGE1_EXTRA, UNITS, LogError, identified_params, identify,
                                       read_log, robot_toml)
    from sim.params import load_params

    stage1 = "" in args.cart_only
    cart_files = [c for c in args.cart_only if c]
    if not args.logs and not cart_files:
        raise A.UsageError("give at least one LOG (a run of upright board excite)")
    A.check_out_file(args.out, "--out")
    A.check_out_file(args.json, "--json")
    params = load_params(args.params)
    try:
        logs = [read_log(p) for p in args.logs] + [read_log(p, cart_only=True) for p in cart_files]
    except LogError as exc:
        raise A.UsageError(str(exc)) from exc
    bals = [lg.name for lg in logs if not lg.cart_only]
    if stage1 and bals:
        raise A.UsageError(f"--cart-only without a file is the first stage (cart-only runs only): {bals[0]} is a "
                           "balancing run (excite column 1)")
    if not bals:
        return _stage1(args, logs, params)
    import warnings

    import numpy as np

    try:
        # numpy's RuntimeWarnings on a degenerate fit are not for the user: the fit either
        # gives finite estimates or fails in one line below
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            res = identify(logs, params, fc=args.fc, max_delay=args.max_delay, n_boot=args.boot)
    except LogError as exc:
        raise A.UsageError(str(exc)) from exc
    except (ValueError, FloatingPointError, ArithmeticError) as exc:
        raise A.RunFailed(f"the fit failed: {exc}") from exc
    e, ci = res["estimates"], res["ci"]
    bad = [k for k in PARAM_NAMES if not math.isfinite(float(e.get(k, math.nan)))]
    if bad:
        raise A.RunFailed(f"the fit failed: no finite estimate of {', '.join(bad)} (the logs do not excite them)")
    print(f"identified from {len(logs)} log(s), {res['rows']} rows; delay {res['delay_samples']} samples")
    src = res.get("sources", {})
    for k in (*PARAM_NAMES, *(x for x in (*STAGE1_EXTRA, "coulomb", "stiction", "backlash") if x in e)):
        lo, hi = ci.get(k, [math.nan, math.nan])
        tag = "  (from --params)" if src.get(k) == "params" else ""
        print(f"  {k:11s} {e[k]:12.6g} {UNITS[k]:8s} 95% [{lo:.6g}, {hi:.6g}]{tag}")
    for n in res["notes"]:
        print(f"  note: {n}")
    if args.out:
        out = identified_params(res, params)
        note = (f"identified by upright identify from {', '.join(lg.name for lg in logs)}\n"
                f"(known from {params.source}: masses, drive, sensor scales; motor.kt = the force constant, "
                f"ke = {e['ke']:.6g} V*s/rad)")
        Path(args.out).write_text(robot_toml(out, note))
        print(f"wrote {args.out} (upright design --params {args.out})", file=sys.stderr)
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=2, default=float) + "\n")
    return 0


def _stage1(args: argparse.Namespace, logs: list, params: object) -> int:
    # the first stage: cart-only runs alone
    import warnings

    import numpy as np

    from host.studies.identify import LogError, identified_params, robot_toml
    from host.studies.identify_cart import CART_NAMES, CART_UNITS, DRY_NAMES, identify_cart

    try:
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            res = identify_cart(logs, params, max_delay=args.max_delay)  # type: ignore[arg-type]
    except LogError as exc:
        raise A.UsageError(str(exc)) from exc
    except (ValueError, FloatingPointError, ArithmeticError) as exc:
        raise A.RunFailed(f"the fit failed: {exc}") from exc
    e, ci = res["estimates"], res["ci"]
    bad = [k for k in ("kt", "ke", "delay") if not math.isfinite(float(e[k]))]
    if bad:
        raise A.RunFailed(f"the fit failed: no finite estimate of {', '.join(bad)}")
    print(f"first stage (cart-only) from {len(logs)} log(s), {res['rows']} rows; delay {res['delay_samples']} "
          f"samples + latency {res['latency_samples']:.2f}")
    for k in (*CART_NAMES, *(x for x in DRY_NAMES if x in e)):
        lo, hi = ci.get(k, [math.nan, math.nan])
        print(f"  {k:11s} {e[k]:12.6g} {CART_UNITS[k]:8s} 95% [{lo:.6g}, {hi:.6g}]")
    for n in res["notes"]:
        print(f"  note: {n}")
    if args.out:
        out = identified_params(res, params)  # type: ignore[arg-type]
        note = (f"first stage of upright identify (cart-only) from {', '.join(lg.name for lg in logs)}\n"
                f"(known from {getattr(params, 'source', '--params')}: masses, drive, sensor scales, the pendulum; "
                "motor.kt = ke, cart.b and sensors.delay identified)")
        Path(args.out).write_text(robot_toml(out, note))
        print(f"wrote {args.out} (upright design --params {args.out})", file=sys.stderr)
    if args.json:
        res = {k: v for k, v in res.items() if k != "fit"}
        Path(args.json).write_text(json.dumps(res, indent=2, default=float) + "\n")
    return 0
