"""``upright export``: the discrete controller as fixed-point tables (``firmware/gains.py``)."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from host.cli import args as A
from host.design.discrete import A_CMD_DEFAULT, OBSERVER_DEFAULT, controller_ss
from host.design.export import ESTIMATORS, V_LIMIT, W_LIMIT, export, render
from host.design.reduced import REDUCED_POLES_DEFAULT, reduced_for
from sim.params import load_params


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright export``."""
    parser.add_argument("--params", default=None, help="robot parameter TOML (default: the report's robot)")
    parser.add_argument("--out", default=None, help="write the gains module here (default: print to stdout)")
    parser.add_argument("--blob", default=None, help="also write the upload bytes (int32 LE) to this file")
    parser.add_argument("--ki", type=A.nonneg, default=0.0, help="integral gain on cart position, N/(m*s)")
    parser.add_argument("--deadband", type=A.int_range(0, 32767), default=0, help="motor deadband compensation, duty counts")
    parser.add_argument("--v-limit", type=A.positive, default=None,
                        help=f"clamp of the cart-speed estimate, m/s (default {V_LIMIT:g})")
    parser.add_argument("--w-limit", type=A.positive, default=None,
                        help=f"clamp of the tilt-rate estimate, rad/s (default {W_LIMIT:g})")
    parser.add_argument("--rate", type=A.in_range(0.0, 10000.0, lo_open=True, unit="Hz"), default=None, help="loop rate in Hz (default: from the parameters)")
    parser.add_argument("--design", choices=("lqr", "place"), default="lqr",
                        help="discrete design: dlqr (weights --Q/--R) or pole placement (the report's poles)")
    parser.add_argument("--Q", type=A.nonneg, nargs=4, default=None, metavar="q", help="LQR state weights (diagonal)")
    parser.add_argument("--R", type=A.positive, default=None, help="LQR input weight")
    parser.add_argument("--u-max", type=A.positive, default=None,
                        help=f"force clamp of the controller, N (default: {A_CMD_DEFAULT:g} m/s^2 of cart acceleration "
                             "from upright)")
    parser.add_argument("--noise", type=A.positive, nargs=2, default=None, metavar=("X_M", "PHI_RAD"),
                        help="measurement noise of the sensors (std, m and rad) (default: one encoder count, two ADC "
                             "counts); the Kalman filter is designed for it divided by --observer")
    parser.add_argument("--observer", type=A.positive, default=None,
                        help=f"estimator speed factor (> 1 trusts the sensors more; default {OBSERVER_DEFAULT:g}, "
                             "the shipped design's)")
    parser.add_argument("--estimator", choices=tuple(ESTIMATORS), default="full",
                        help="full: the Kalman filter of the four states (default, the shipped table); reduced: the "
                             "reduced-order observer of xdot and phidot, x and phi straight from the sensors "
                             "(docs/design.md)")
    parser.add_argument("--reduced-poles", type=_poles, default=None, metavar="P1,P2",
                        help="continuous poles of the reduced-order observer, rad/s (default "
                             + ",".join(f"{v:g}" for v in REDUCED_POLES_DEFAULT) + "; with --estimator reduced)")


def _poles(text: str) -> tuple[complex, complex]:
    # "P1,P2": two stable poles (a real pair or a conjugate pair such as -5+2j,-5-2j)
    try:
        vals = tuple(complex(w.strip().replace(" ", "")) for w in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two poles P1,P2, got {text!r}") from None
    if len(vals) != 2 or not all(math.isfinite(v.real) and math.isfinite(v.imag) and v.real < 0 for v in vals):
        raise argparse.ArgumentTypeError(f"expected two stable poles (negative real part) P1,P2, got {text!r}")
    if vals[0].imag != 0 and vals[0] != vals[1].conjugate():
        raise argparse.ArgumentTypeError(f"complex poles come in conjugate pairs, got {text!r}")
    return vals[0], vals[1]


def run(args: argparse.Namespace) -> int:
    """Export the fixed-point tables (``upright export``)."""
    A.check_out_file(args.out, "--out")
    A.check_out_file(args.blob, "--blob")
    p = load_params(args.params)
    if args.rate is not None:
        ticks = p.delay * args.rate
        if abs(ticks - round(ticks)) > 1e-6:
            raise A.UsageError(f"--rate {args.rate:g}: the measurement delay {p.delay:g} s (sensors.delay) would be "
                               f"{ticks:.4g} ticks; choose a rate at which it is a whole number of ticks")
    if args.design != "lqr" and (args.Q is not None or args.R is not None):
        raise A.UsageError(f"--Q/--R are LQR weights: they do not apply to --design {args.design}")
    kw: dict[str, object] = {} if args.noise is None else {"sigma_meas": tuple(args.noise)}
    if args.observer is not None:
        kw["observer"] = args.observer
    if args.estimator != "reduced" and args.reduced_poles is not None:
        raise A.UsageError("--reduced-poles: the poles of the reduced-order observer need --estimator reduced")
    if args.estimator == "reduced" and (args.noise is not None or args.observer is not None):
        raise A.UsageError("--noise/--observer design the Kalman filter: they do not apply to --estimator reduced "
                           "(its poles: --reduced-poles)")
    c = controller_ss(p, rate=args.rate, design=args.design, Q=args.Q, R=args.R, u_max=args.u_max, **kw)
    if args.estimator == "reduced":
        c = reduced_for(p, c, args.reduced_poles)
    fd = export(p, c, ki=args.ki, deadband=args.deadband, v_limit=args.v_limit, w_limit=args.w_limit)
    text = render(fd)
    if args.out:
        Path(args.out).write_text(text)
        print(f"wrote {args.out} ({len(fd.flat())} ints, crc 0x{fd.crc():04X})", file=sys.stderr)
    else:
        sys.stdout.write(text)
    if args.blob:
        Path(args.blob).write_bytes(fd.blob())
    return 0
