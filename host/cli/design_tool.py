"""``upright design`` with design flags: the toolkit on the command line (:mod:`host.design.toolkit`).

Any of ``--Q/--R``, ``--poles``, ``--spec``, ``--observer-poles``, ``--noise``,
``--reduced-poles``, ``--pid``, ``--rate``, ``--delay`` or ``--json`` (without ``--robust``)
turns ``upright design`` from the fixed report into this: the chosen designs, continuous and
(with ``--rate``) discrete, printed, and with ``--json FILE`` (``-``: stdout) written as JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any, Callable

import numpy as np

TOOL_FLAGS = ("Q", "R", "poles", "spec", "observer_poles", "noise", "reduced_poles", "pid", "rate", "delay")
"""The attributes of the design flags (any of them selects the toolkit)."""


def _numbers(n: int | None, what: str, parse: Callable[[str], Any] = float) -> Callable[[str], list[Any]]:
    def check(text: str) -> list[Any]:
        try:
            vals = [parse(t.strip().replace("i", "j")) for t in text.split(",") if t.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what} separated by commas, got {text!r}") from None
        if n is not None and len(vals) != n:
            raise argparse.ArgumentTypeError(f"expected {n} {what}, got {len(vals)} in {text!r}")
        if not all(math.isfinite(abs(v)) for v in vals):
            raise argparse.ArgumentTypeError(f"every value must be finite, got {text!r}")
        return vals

    check.__name__ = what
    return check


def add_tool_arguments(parser: argparse.ArgumentParser) -> None:
    """The design flags of ``upright design``."""
    from host.cli.args import nonneg, positive

    import re

    if hasattr(parser, "_negative_number_matcher"):  # let "--poles -2,-3,..." read as a value (no flag starts -<digit>)
        parser._negative_number_matcher = re.compile(r"^-\.?\d")
    g = parser.add_argument_group("design flags (the toolkit; docs/design.md)",
                                  "comma-separated lists; complex poles as -4+1j: --poles -2,-3,-4+1j,-4-1j")
    g.add_argument("--Q", type=_numbers(4, "weights"), metavar="QX,QXD,QPHI,QPHID",
                   help="LQR state weights, the diagonal of Q (with --R)")
    g.add_argument("--R", type=positive, metavar="R", help="LQR input weight (with --Q)")
    g.add_argument("--poles", type=_numbers(4, "poles", complex), metavar="P1,..,P4",
                   help="pole placement: 4 closed-loop poles (complex as -4+1j)")
    g.add_argument("--spec", type=_numbers(2, "numbers"), metavar="OVERSHOOT,SETTLING",
                   help="pole placement from a step spec (fraction, s), the report's section 3.2")
    g.add_argument("--observer-poles", type=_numbers(4, "poles", complex), metavar="P1,..,P4",
                   help="full-order Luenberger observer poles")
    g.add_argument("--noise", type=_numbers(3, "noise levels"), metavar="SF,SX,SPHI",
                   help="Kalman filter: force noise (N), x noise (m), phi noise (rad), standard deviations")
    g.add_argument("--reduced-poles", type=_numbers(2, "poles", complex), metavar="P1,P2",
                   help="reduced-order observer of xdot and phidot: 2 poles")
    g.add_argument("--pid", type=_numbers(3, "gains"), metavar="KP,KI,KD", help="PID on the angle")
    g.add_argument("--rate", type=positive, metavar="HZ", help="loop rate: add the discrete design (ZOH)")
    g.add_argument("--delay", type=nonneg, metavar="S",
                   help="measurement delay (s, whole ticks at --rate; default the robot file's sensors.delay, 0 without)")


def wants_tool(args: argparse.Namespace) -> bool:
    """True when any design flag is given (or ``--json`` without ``--robust``)."""
    return any(getattr(args, k, None) is not None for k in TOOL_FLAGS) or (
        getattr(args, "json", None) is not None and not getattr(args, "robust", False))


def _check(args: argparse.Namespace, params: Any) -> tuple[float | None, float]:
    from host.cli.args import UsageError
    from sim.robot_file import missing_sections

    if (args.Q is None) != (args.R is None):
        raise UsageError("--Q and --R go together (the LQR weights)")
    if args.Q is not None and any(q < 0 for q in args.Q):
        raise UsageError(f"--Q: weights must be >= 0, got {args.Q}")
    if args.poles is not None and args.spec is not None:
        raise UsageError("--poles and --spec both give the placement poles: one of them")
    if args.spec is not None and not (0 < args.spec[0] < 1 and args.spec[1] > 0):
        raise UsageError(f"--spec: overshoot must be a fraction in (0, 1) and settling > 0 s, got {args.spec}")
    if args.noise is not None and not all(v > 0 for v in args.noise):
        raise UsageError(f"--noise: standard deviations must be > 0, got {args.noise}")
    for flag, val in (("--poles", args.poles), ("--observer-poles", args.observer_poles),
                      ("--reduced-poles", args.reduced_poles)):
        if val is not None:
            p = np.asarray(val, complex)
            if np.any(p.real >= 0):
                raise UsageError(f"{flag}: every pole needs a negative real part, got {val}")
            if not np.allclose(np.sort_complex(p), np.sort_complex(np.conj(p))):
                raise UsageError(f"{flag}: complex poles come in conjugate pairs, got {val}")
    missing = missing_sections(params.values)
    rate = args.rate if args.rate is not None else (None if "loop" in missing else float(params.rate))
    if args.delay is not None:
        delay = float(args.delay)
        if rate is None:
            raise UsageError(f"--delay needs --rate ({params.source} has no [loop] section)")
    else:
        delay = 0.0 if "sensors" in missing else float(params.delay)
    if rate is not None:
        if rate > 100_000:
            raise UsageError(f"--rate: at most 100000 Hz, got {rate:g}")
        ticks = delay * rate
        if abs(ticks - round(ticks)) > 1e-6:
            flag = "--delay" if args.delay is not None else "sensors.delay"
            raise UsageError(f"{flag}: {delay:g} s is not a whole number of ticks of {1e3 / rate:g} ms "
                             f"(rate {rate:g} Hz: {ticks:.4g} ticks)")
    return rate, delay


def _fmt_c(v: list[float]) -> str:
    re, im = v
    return f"{re:.5g}{im:+.5g}j" if abs(im) > 1e-9 else f"{re:.5g}"


def _mat(a: Any) -> str:
    return np.array2string(np.asarray(a, float), precision=5, suppress_small=True, max_line_width=120)


def render(d: dict[str, Any]) -> str:
    """The toolkit's result as text (every number of the JSON that a person reads)."""
    out = ["Conventions:"] + [f"  {k}: {v}" for k, v in d["conventions"].items()]
    r = d["robot"]
    out.append(f"\nRobot {r['source']}: M {r['M']:g} kg, m {r['m']:g} kg, b {r['b']:g} N*s/m, L_cm {r['L_cm']:.6g} m, "
               f"I_cm {r['I_cm']:.6g} kg*m^2 (I_pivot {r['I_pivot']:.6g}), g {r['g']:g} m/s^2"
               + (f"; sections not given: {', '.join(r['missing_sections'])}" if r["missing_sections"] else ""))
    p = d["plant"]
    out += ["\nPlant (linearised about upright)", "A =", _mat(p["A"]), "B =", _mat(p["B"]), "C =", _mat(p["C"]),
            "open-loop poles: " + ", ".join(_fmt_c(v) for v in p["poles"])]
    for k, tf in p["tf"].items():
        out.append(f"P_{k}(s): num {np.round(tf['num'], 6).tolist()}, den {np.round(tf['den'], 6).tolist()}; "
                   f"zeros {', '.join(_fmt_c(v) for v in tf['zeros']) or 'none'}")
    out.append(f"controllability: det Wr {p['controllability']['det_Wr']:.6g}, rank {p['controllability']['rank']}; "
               f"observability rank [x, phi]: {p['observability']['rank']}")
    for name in ("lqr", "place"):
        if name in d:
            s = d[name]
            out.append(f"\n{name.upper()}: K = {np.round(s['K'], 6).tolist()}, Nbar = {s['Nbar']:.6g}; poles "
                       + ", ".join(_fmt_c(v) for v in s["poles"]))
    for name in ("observer", "kalman"):
        if name in d:
            out += [f"\n{name}: poles " + ", ".join(_fmt_c(v) for v in d[name]["poles"]), "L =", _mat(d[name]["L"])]
    if "reduced_observer" in d:
        ro = d["reduced_observer"]
        out += ["\nreduced-order observer: poles " + ", ".join(_fmt_c(v) for v in ro["poles"]), "Lr =", _mat(ro["Lr"])]
    if "pid" in d:
        pd = d["pid"]
        out.append(f"\nPID: closed-loop poles {', '.join(_fmt_c(v) for v in pd['closed_loop_poles'])}; margins {pd['margins']}")
    for name, c in d.get("controllers", {}).items():
        extra = ("; closed-loop poles " + ", ".join(_fmt_c(v) for v in c["closed_loop_poles"])) if "closed_loop_poles" in c else ""
        out.append(f"{name}: margins {c['margins']}{extra}")
    if "discrete" in d:
        dd = d["discrete"]
        out += [f"\nDiscrete (ZOH) at {dd['rate']:g} Hz, Ts {dd['Ts']:g} s, delay {dd['delay']:g} s = {dd['delay_steps']} ticks",
                "Ad =", _mat(dd["plant"]["A"]), "Bd =", _mat(dd["plant"]["B"])]
        for name in ("lqr", "place"):
            if name in dd:
                out.append(f"{name} (discrete): K = {np.round(dd[name]['K'], 6).tolist()}, Nbar = {dd[name]['Nbar']:.6g}")
        for name in ("observer", "kalman"):
            if name in dd:
                out += [f"{name} (discrete): Ld =", _mat(dd[name]["L"])]
        if "reduced_observer" in dd:
            out += ["reduced-order observer (discrete): Lr =", _mat(dd["reduced_observer"]["Lr"])]
        for k, v in dd.get("controllers", {}).items():
            big = [_fmt_c(z) for z in v["closed_loop_poles"] if math.hypot(*z) > 0.05]
            out.append(f"{k} with the delay: {len(v['Ac'])} controller states, closed-loop poles (|z| > 0.05; the rest "
                       f"the delay line's, near 0) {', '.join(big)}")
    return "\n".join(out)


def run_tool(args: argparse.Namespace) -> int:
    """The design flags' run: compute, print, write the JSON."""
    from host.cli.args import UsageError, check_out_file
    from host.design import toolkit
    from sim.params import load_params

    if getattr(args, "uncertainty", None) is not None:
        raise UsageError("--uncertainty needs --robust")
    check_out_file(args.json, "--json")
    params = load_params(args.params)
    rate, delay = _check(args, params)
    try:
        result = toolkit.design(
            params, Q=args.Q, R=args.R, poles=args.poles, spec=tuple(args.spec) if args.spec else None,
            observer_poles=args.observer_poles, noise=args.noise, reduced_poles=args.reduced_poles,
            pid_gains=args.pid, rate=rate, delay=delay)
    except ValueError as exc:  # a design python-control cannot make (placement of uncontrollable poles, ...)
        raise UsageError(str(exc)) from exc
    text = json.dumps(result, indent=1)
    if args.json == "-":
        sys.stdout.write(text + "\n")
        return 0
    print(render(result))
    if args.json is not None:
        from pathlib import Path

        Path(args.json).write_text(text + "\n")
        print(f"\njson: {args.json}")
    return 0
