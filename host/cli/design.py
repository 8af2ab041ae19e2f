"""``upright design``: the design report of the robot in the parameter file, or (with design
flags: ``--Q/--R``, ``--poles``, ``--observer-poles``, ``--noise``, ``--reduced-poles``, ``--pid``,
``--rate``, ``--delay``, ``--json``) the chosen designs (:mod:`host.cli.design_tool`).

Without flags it prints tables of open-loop poles, gains, closed-loop poles, margins and constraint checks
for every design, and writes figures (pole-zero map, step/impulse responses, Nyquist
plots, gang-of-four Bode) as PNG files.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np

from host.design import analysis
from host.design import controllers as design
from sim.params import RobotParams, load_params
from sim.plant import linear_model, simulate


def _fmt(v: Any) -> str:
    if isinstance(v, complex) or (isinstance(v, np.generic) and np.iscomplexobj(v)):
        v = complex(v)
        return f"{v.real:.4g}{v.imag:+.4g}j" if abs(v.imag) > 1e-9 else f"{v.real:.4g}"
    if isinstance(v, float):
        return "inf" if math.isinf(v) else f"{v:.4g}"
    return str(v)


def poly_str(coeffs: np.ndarray) -> str:
    """A polynomial in s, highest power first, e.g. ``s^3 + 0.1644 s^2 - 23.68 s``."""
    n = len(coeffs) - 1
    terms = []
    for i, c in enumerate(coeffs):
        if c == 0:
            continue
        p = n - i
        mag = "" if abs(c) == 1 and p else f"{abs(c):.4g}"
        var = "" if p == 0 else ("s" if p == 1 else f"s^{p}")
        terms.append(("- " if c < 0 else "+ ") + (mag + (" " if mag and var else "") + var))
    text = " ".join(terms) or "0"
    return text[2:] if text.startswith("+ ") else "-" + text[2:]


def table(headers: list[str], rows: list[list[Any]]) -> str:
    """Render a plain-text table."""
    cells = [[_fmt(c) for c in r] for r in rows]
    w = [max(len(h), *(len(r[i]) for r in cells)) for i, h in enumerate(headers)]
    line = "  ".join(h.ljust(w[i]) for i, h in enumerate(headers))
    out = [line, "  ".join("-" * x for x in w)]
    out += ["  ".join(c.ljust(w[i]) for i, c in enumerate(r)) for r in cells]
    return "\n".join(out)


def build_report(params: RobotParams, search: bool = True) -> tuple[str, dict[str, Any]]:
    """Compute the design report.

    Parameters
    ----------
    params : RobotParams
    search : bool
        Run the LQR weight grid search (a few seconds).

    Returns
    -------
    text : str
        The printable report.
    data : dict
        The numbers behind it (gains, poles, scores, loop analyses).
    """
    A, B, C, _ = linear_model(params)
    parts: list[str] = []
    data: dict[str, Any] = {}
    tfs = analysis.transfer_functions(params)
    parts.append("Plant (linearised about upright), state [x, xdot, phi, phidot], input F (N)")
    parts.append(table(["open-loop pole"], [[p] for p in np.linalg.eigvals(A)]))
    for key in ("phi", "x"):
        num, den = (np.atleast_1d(np.squeeze(getattr(tfs[key], a)[0][0])) for a in ("num", "den"))
        parts.append(f"P_{key}(s) = ({poly_str(num)}) / ({poly_str(den)})")
    _, det_wr, rank_wr = analysis.controllability(A, B)
    parts.append(f"det Wr = {det_wr:.5g} (rank {rank_wr}), rank Wo [x, phi] = {analysis.observability_rank(A, C)}")
    sens = analysis.single_sensor_observability(params)
    parts.append(
        table(
            ["model", "sensor", "rank Wo", "observable", "det Wo(1 s)"],
            [[o.model, o.sensor, o.rank, o.observable, o.volume] for o in sens],
        )
    )

    cons = design.Constraints.from_params(params)
    zeta, omega = design.zeta_omega_from_spec(0.08, 0.84)
    gains = {"place": design.place_gain(params), "lqr": design.lqr_gain(params)}
    rows = []
    for name, K in gains.items():
        kr = design.precompensator(params, K)
        cl = np.linalg.eigvals(A - B @ K[None, :])
        sc = design.score_state_feedback(params, K, step=0.2)
        rows.append([name, ", ".join(f"{k:.2f}" for k in K), kr, ", ".join(_fmt(p) for p in sorted(cl, key=lambda z: z.real)), sc.peak_phi, sc.settling, sc.peak_accel, "PASS" if sc.ok else "FAIL"])
        data[name] = {"K": K.tolist(), "kr": kr, "score": sc}
    parts.append(f"\nState feedback (spec: 8 % overshoot, 0.84 s settling -> zeta {zeta:.3f}, omega {omega:.3f} rad/s)")
    parts.append(f"Scored on a 20 cm cart step, nonlinear plant; constraints |phi| < {cons.phi_max} rad, settling < {cons.t_settle} s, |xddot| <= {cons.a_max} m/s^2")
    parts.append(table(["design", "K", "kr", "closed-loop poles", "peak |phi|", "settling s", "peak xddot", "constraints"], rows))
    L, lpoles = design.observer_gain(params, gains["place"])
    parts.append("Observer poles (10x the slowest controller pole): " + ", ".join(_fmt(p) for p in lpoles))
    data["observer_L"] = L.tolist()
    if search:
        ranked = design.lqr_weight_search(params)
        parts.append("\nLQR weight search (R = 0.001), best first:")
        parts.append(
            table(
                ["q_x", "q_phi", "peak |phi|", "settling s", "peak xddot", "peak F", "constraints"],
                [[w[0], w[1], s.peak_phi, s.settling, s.peak_accel, s.peak_force, "PASS" if s.ok else "FAIL"] for w, s in ranked[:6]],
            )
        )
        data["lqr_search"] = [(w, s) for w, s in ranked]

    import control as ct

    s = ct.tf("s")
    loops = {
        "(s+1)^2/s": (s + 1) ** 2 / s,
        "10 (s+1)^2/s": 10 * (s + 1) ** 2 / s,
        "20 (s+1)(s+10)/s": design.loop_controller(*design.REPORT_LOOP),
        "PID [79.95,125.4,8.24]": design.pid_tf(),
    }
    rows = []
    for name, Cs in loops.items():
        la = design.analyse_loop(params, Cs)
        gang = " ".join(f"{k}:{'ok' if v['stable'] else 'UNSTABLE'}" for k, v in la.gang.items())
        rows.append([name, la.open_loop_rhp, la.encirclements, la.closed_loop_rhp, "yes" if la.stable else "no", la.gain_margin, la.phase_margin, la.ms, la.mt, gang])
        data[name] = la
    kc = design.critical_gain(params, (s + 1) ** 2 / s)
    parts.append("\nAngle loop L = P_phi C, negative feedback (Nyquist: Z = N + P, N clockwise)")
    parts.append(table(["C(s)", "P", "N", "Z", "stable", "GM", "PM deg", "Ms", "Mt", "gang of four"], rows))
    parts.append(
        f"Critical gain of (s+1)^2/s: {kc:.4f} (report: ~3.7).  CS keeps the integrator that cancels the\n"
        "plant's zero at s = 0 (a pole at the origin: the cart drifts) and is improper (unbounded noise gain);\n"
        "the firmware uses the state-feedback design, which controls the cart position as well."
    )
    data["critical_gain"] = kc
    return "\n".join(parts), data


def write_figures(params: RobotParams, out: Path) -> list[Path]:
    """Write the design figures as PNG into ``out`` and return their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import control as ct
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    A, B, C, D = linear_model(params)
    written = []

    fig, ax = plt.subplots(figsize=(6, 4.5))
    ol = np.linalg.eigvals(A)
    K = design.place_gain(params)
    cl = np.linalg.eigvals(A - B @ K[None, :])
    Kl = design.lqr_gain(params)
    cll = np.linalg.eigvals(A - B @ Kl[None, :])
    zeros = analysis.transfer_functions(params)["phi"].zeros()
    ax.plot(ol.real, ol.imag, "kx", ms=10, label="open-loop poles")
    ax.plot(zeros.real, zeros.imag, "ko", mfc="none", ms=9, label="zeros of P_phi")
    ax.plot(cl.real, cl.imag, "C0x", ms=9, label="pole placement")
    ax.plot(cll.real, cll.imag, "C1+", ms=11, label="LQR")
    ax.axvline(0, color="0.6", lw=0.8)
    ax.set(xlabel="Re (1/s)", ylabel="Im (rad/s)", title="Pole-zero map")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    written.append(out / "pole_zero.png")
    fig.savefig(written[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)

    fig, axes = plt.subplots(2, 2, figsize=(10, 6), sharex=True)
    for name in ("place", "lqr", "place-observer", "pid", "loopshape"):
        step = design.make_controller(params, name, reference=0.2)
        res = simulate(params, [0, 0, 0, 0], 5.0, controller=step, dt=2e-3, substeps=2)
        axes[0, 0].plot(res["t"], res["x"], label=name)
        axes[1, 0].plot(res["t"], res["phi"], label=name)
        imp = simulate(params, [0, 0, 0, 0], 5.0, controller=design.make_controller(params, name, dt=2e-3), force=lambda t: 10.0 if t < 0.02 else 0.0, dt=2e-3, substeps=2)
        axes[0, 1].plot(imp["t"], imp["x"], label=name)
        axes[1, 1].plot(imp["t"], imp["phi"], label=name)
    axes[0, 0].set(title="20 cm reference step", ylabel="x (m)")
    axes[1, 0].set(ylabel="phi (rad)", xlabel="t (s)")
    axes[0, 1].set(title="impulse kick (10 N for 20 ms)")
    axes[1, 1].set(xlabel="t (s)")
    for a in axes.ravel():
        a.grid(alpha=0.3)
    for a in axes[1]:
        a.axhspan(-params.phi_max, params.phi_max, color="g", alpha=0.06)
    axes[0, 0].legend(fontsize=8)
    written.append(out / "responses.png")
    fig.savefig(written[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)

    s = ct.tf("s")
    P = analysis.transfer_functions(params)["phi"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    cases = [("C = (s+1)^2/s", (s + 1) ** 2 / s, 0.6), ("C = 20 (s+1)(s+10)/s", design.loop_controller(*design.REPORT_LOOP), 4.0)]
    for ax, (title, Cs, lim) in zip(axes, cases):
        L = analysis.clean_tf(ct.minreal(P * Cs, verbose=False))
        w = np.logspace(-3, 3, 4000)
        resp = L(1j * w)
        ax.plot(resp.real, resp.imag, "C0")
        ax.plot(resp.real, -resp.imag, "C0--", alpha=0.6)
        ax.plot([-1], [0], "r+", ms=12)
        ax.set(xlim=(-lim * 3, lim), ylim=(-lim * 2, lim * 2), title=f"Nyquist, {title}", xlabel="Re", ylabel="Im")
        ax.grid(alpha=0.3)
    written.append(out / "nyquist.png")
    fig.savefig(written[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)

    Cs = design.loop_controller(*design.REPORT_LOOP)
    fig, axes = plt.subplots(2, 2, figsize=(10, 6), sharex=True)
    w = np.logspace(-2, 3, 800)
    labels = {"S": "S = 1/(1+PC)", "T": "T = PC/(1+PC)", "PS": "PS = P/(1+PC)", "CS": "CS = C/(1+PC)"}
    for ax, (key, (num, den)) in zip(axes.ravel(), design.gang_of_four(P, Cs).items()):
        name = labels[key]
        mag = np.abs(np.polyval(num, 1j * w) / np.polyval(den, 1j * w))
        ax.semilogx(w, 20 * np.log10(np.maximum(mag, 1e-12)))
        ax.set(title=name, ylabel="dB")
        ax.grid(alpha=0.3, which="both")
    for ax in axes[1]:
        ax.set(xlabel="omega (rad/s)")
    fig.suptitle("Gang of four, C(s) = 20 (s+1)(s+10)/s")
    written.append(out / "gang_of_four.png")
    fig.savefig(written[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)
    return written


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright design``."""
    parser.add_argument("--params", metavar="TOML", help="parameter file (default: the report's robot)")
    parser.add_argument("--out", default="out/design", help="directory for the PNG figures")
    parser.add_argument("--no-figures", action="store_true", help="print the report only")
    parser.add_argument("--no-search", action="store_true", help="skip the LQR weight search")
    from host.cli.args import nonneg_int, positive_int

    parser.add_argument("--robust", action="store_true",
                        help="robust design: the weights, estimator and force clamp with the best worst case over "
                             "the uncertainty set (sim/uncertainty.toml)")
    parser.add_argument("--uncertainty", metavar="TOML", default=None,
                        help="--robust: uncertainty set replacing sim/uncertainty.toml's keys")
    parser.add_argument("--candidates", type=positive_int, default=24,
                        help="--robust: designs evaluated (the budget; default 24, a few minutes on 2 cores)")
    parser.add_argument("--seed", type=nonneg_int, default=0, help="--robust: seed of the candidate draw")
    parser.add_argument("--json", metavar="FILE", default=None,
                        help="write the result as JSON: --robust's, or the design flags' ('-': stdout, nothing else)")
    from host.cli.design_tool import add_tool_arguments

    add_tool_arguments(parser)


def run(args: argparse.Namespace) -> int:
    """Print the design report and write the figures."""
    from host.cli.args import check_out_dir

    from host.cli.design_tool import TOOL_FLAGS, run_tool, wants_tool

    if getattr(args, "robust", False):
        from host.cli.args import UsageError
        from host.cli.design_robust import run_robust

        given = [f"--{k.replace('_', '-')}" for k in TOOL_FLAGS if getattr(args, k, None) is not None]
        if given:
            raise UsageError(f"{given[0]}: a design flag, not with --robust")

        return run_robust(args)
    if wants_tool(args):
        return run_tool(args)
    if getattr(args, "uncertainty", None) is not None:
        from host.cli.args import UsageError

        raise UsageError("--uncertainty needs --robust")
    if not args.no_figures:
        check_out_dir(args.out, "--out")
    params = load_params(args.params)
    from sim.robot_file import missing_sections

    if "loop" in missing_sections(params.values):
        from host.cli.args import UsageError

        raise UsageError(f"the report scores every design against the [loop] constraints, and {params.source} has no "
                         f"[loop] section: add it, or design with the flags (--Q/--R, --poles, ...; docs/design.md)")
    text, _ = build_report(params, search=not args.no_search)
    print(f"Design report for {params.source}\n")
    print(text)
    if not args.no_figures:
        paths = write_figures(params, Path(args.out))
        print("\nfigures: " + ", ".join(str(p) for p in paths))
    return 0
