"""``upright sweep``: batch Monte Carlo with the vectorised closed-loop simulator.

Three sweeps (see :mod:`host.studies.sweep`)::

    upright sweep robustness [--n 1000]   # parameter uncertainty, delay 5-20 ms, noise, tilts
    upright sweep tune [--n 200]          # LQR weights x observer speed, scored by robustness
    upright sweep tilt                    # largest recoverable initial tilt vs atan(a_max/g)
    upright sweep hil [--n 8] [--workers 2]  # HIL Monte Carlo: the firmware on the MicroPython unix port

``--ranges FILE`` takes the Monte Carlo ranges from a TOML file (:mod:`host.studies.ranges`)
instead of the defaults.

Every sweep runs in this process, or on a Dask cluster with ``--scheduler tcp://host:port``
(same results for the same ``--seed``).  Results go to ``--out`` as CSV and Parquet, with
PNG plots; the robustness sweep also writes its worst runs as replayable scenario TOML
files (``upright simulate`` / :func:`sim.scenario.load_scenario` read them).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from host.cli import args as A

__all__ = ["add_arguments", "run", "parse_noise", "write_table", "ProgressBar"]

KINDS = ("robustness", "tune", "tilt", "hil")


def parse_noise(spec: str) -> Any:
    """``"none"``, ``"uniform:AMPLITUDE"`` or ``"white:POWER"`` -> :class:`sim.sensors.NoiseModel`.

    Raises
    ------
    ValueError
        On an unknown kind or a bad number.
    """
    from sim.sensors import NoiseModel

    kind, _, val = spec.partition(":")
    if kind == "none" and not val:
        return NoiseModel()
    if kind not in ("uniform", "white") or not val:
        raise ValueError(f"--noise must be 'none', 'uniform:AMPLITUDE' or 'white:POWER', got {spec!r}")
    try:
        v = float(val)
    except ValueError as exc:
        raise ValueError(f"--noise {spec!r}: {val!r} is not a number") from exc
    return NoiseModel(kind, amplitude=v) if kind == "uniform" else NoiseModel(kind, power=v)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright sweep``."""
    parser.add_argument("kind", choices=KINDS, help="which sweep")
    parser.add_argument("--n", type=A.positive_int, default=None,
                        help="runs (robustness, default 1000) or runs per design (tune, default 100)")
    parser.add_argument("--seed", type=A.nonneg_int, default=0, help="base seed (runs are seeded per run)")
    parser.add_argument("--scheduler", default=None, metavar="ADDR", type=A.scheduler_address,
                        help="Dask scheduler, e.g. tcp://host:8786")
    parser.add_argument("--out", default="out/sweep", help="output directory (CSV, Parquet, PNG, scenarios)")
    parser.add_argument("--params", default=None, metavar="TOML", help="robot parameter file (default sim/robot.toml)")
    from host.cli.plant import add_plant_argument

    add_plant_argument(parser)
    parser.add_argument("--chunk", type=A.positive_int, default=500, help="runs per task")
    parser.add_argument("--duration", type=float, default=5.0, help="simulated seconds per run")
    parser.add_argument("--noise", default="uniform:0.001", metavar="SPEC",
                        help="measurement noise: none | uniform:AMPLITUDE | white:POWER (default uniform:0.001)")
    parser.add_argument("--drive", choices=("motor", "force"), default="motor",
                        help="motor: duty through the DC motor model; force: ideal force actuator")
    parser.add_argument("--tilt0", type=A.in_range(0.0, math.pi / 2, hi_open=True, unit="rad"), default=None,
                        help="robustness: initial tilt range +-rad (default 0.03, or the ranges file's tilt)")
    parser.add_argument("--ranges", metavar="TOML", default=None,
                        help="robustness, hil: Monte Carlo ranges from a TOML file (mass, inertia, friction, motor, "
                             "delay, tilt; e.g. sim/sweep_ranges.toml) instead of the defaults")
    parser.add_argument("--scenario", default="tilt_0p1", metavar="NAME|TOML",
                        help="hil: the scenario every run closes through the firmware (default tilt_0p1)")
    parser.add_argument("--workers", type=A.positive_int, default=None,
                        help="hil: start a local Dask cluster of N worker processes (one MicroPython board each)")
    parser.add_argument("--u-max", type=A.positive, default=None, dest="u_max", help="controller force saturation (N)")
    parser.add_argument("--q-x", type=A.nonneg, default=None, dest="q_x", help="design: LQR weight on x (robustness, tilt)")
    parser.add_argument("--q-phi", type=A.nonneg, default=None, dest="q_phi", help="design: LQR weight on phi")
    parser.add_argument("--r", type=float, default=None, help="design: LQR input weight R")
    parser.add_argument("--observer", type=float, default=None,
                        help="design: observer speed factor (>1 faster; default the shipped design's)")
    parser.add_argument("--worst", type=A.nonneg_int, default=5, help="robustness: worst runs exported as scenarios")
    parser.add_argument("--search", choices=("grid", "random"), default="grid", help="tune: grid or random search")
    parser.add_argument("--designs", type=A.positive_int, default=20, help="tune --search random: number of designs")
    parser.add_argument("--step", type=A.in_range(0.0, 1.0, lo_open=True, unit="rad"), default=0.005,
                        help="tilt: tilt grid step (rad)")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


class ProgressBar:
    """A one-line text progress bar on a stream: ``[#####.....] 50% 500/1000 runs 3.2 s``."""

    def __init__(self, label: str, stream: Any = None, width: int = 30, enabled: bool = True) -> None:
        self.label = label
        self.stream = sys.stderr if stream is None else stream
        self.width = width
        self.enabled = enabled
        self.t0 = time.perf_counter()
        self._last = -1.0

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        if done < total and now - self._last < 0.2:
            return
        self._last = now
        frac = done / total if total else 1.0
        fill = int(round(frac * self.width))
        el = now - self.t0
        eta = f" eta {el / frac - el:5.1f} s" if 0 < frac < 1 else ""
        self.stream.write(f"\r{self.label} [{'#' * fill}{'.' * (self.width - fill)}] {frac:4.0%} {done}/{total} runs {el:6.1f} s{eta}  ")
        if done >= total:
            self.stream.write("\n")
        self.stream.flush()


def write_table(cols: Mapping[str, Any], stem: Path) -> list[Path]:
    """Write equal-length columns as ``stem.csv`` and ``stem.parquet``; the paths written."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    names = list(cols)
    arrays = [np.asarray(cols[k]) for k in names]
    stem.parent.mkdir(parents=True, exist_ok=True)
    csv_path = stem.with_suffix(".csv")
    with csv_path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(names)
        for row in zip(*arrays):
            w.writerow([_cell(v) for v in row])
    pq_path = stem.with_suffix(".parquet")
    pq.write_table(pa.table({k: a for k, a in zip(names, arrays)}), pq_path)
    return [csv_path, pq_path]


def _cell(v: Any) -> str:
    if isinstance(v, (bool, np.bool_)):
        return "1" if v else "0"
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    return str(v)


def _rows_to_cols(rows: Sequence[Mapping[str, Any]]) -> dict[str, list[Any]]:
    keys = list(dict.fromkeys(k for r in rows for k in r))
    return {k: [r.get(k, "") for r in rows] for k in keys}


def _fmt_table(rows: Sequence[Mapping[str, Any]], cols: Sequence[str]) -> str:
    def f(v: Any) -> str:
        if isinstance(v, (bool, np.bool_)):
            return "yes" if v else ""
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    cells = [[f(r.get(c, "")) for c in cols] for r in rows]
    w = [max(len(c), *(len(x[i]) for x in cells)) if cells else len(c) for i, c in enumerate(cols)]
    lines = ["  ".join(c.ljust(n) for c, n in zip(cols, w)), "  ".join("-" * n for n in w)]
    lines += ["  ".join(x.ljust(n) for x, n in zip(row, w)) for row in cells]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Run the selected sweep; print a summary; write tables, plots and scenarios."""
    from sim.params import load_params
    from host.studies.sweep import Design, SweepConfig, Uncertainty

    if not 0 < args.duration <= A.MAX_DURATION_S:
        raise A.UsageError(f"--duration must be in (0, {A.MAX_DURATION_S:g}] s, got {args.duration}")
    if args.r is not None and not (math.isfinite(args.r) and args.r > 0):
        raise A.UsageError(f"--r: the LQR input weight must be finite with R > 0, got {args.r}")
    unc = _ranges(args)
    if args.worst < 0:
        raise A.UsageError(f"--worst must be >= 0, got {args.worst}")
    out = A.check_out_dir(args.out, "--out")
    params = load_params(args.params)
    from host.cli.plant import load_plant

    plant = load_plant(getattr(args, "plant", None), params)
    try:
        noise = parse_noise(args.noise)
    except ValueError as exc:
        raise A.UsageError(str(exc)) from exc
    out.mkdir(parents=True, exist_ok=True)
    bar = ProgressBar(f"sweep {args.kind}", enabled=not args.quiet)
    base = SweepConfig(params=params, design=_chosen_design(args), uncertainty=unc,
                       seed=args.seed, duration=args.duration, noise=noise, drive=args.drive, plant=plant)
    where = f"on Dask at {args.scheduler}" if args.scheduler else (
        f"on {args.workers} local Dask workers" if getattr(args, "workers", None) else "in this process")
    print(f"upright sweep {args.kind}: seed {args.seed}, noise {args.noise}, drive {args.drive}, {where}")
    if args.ranges is not None:
        print(f"ranges from {args.ranges}: mass +-{unc.mass:g}, inertia +-{unc.inertia:g}, friction x{unc.friction[0]:g}"
              f"..x{unc.friction[1]:g}, motor +-{unc.motor:g}, delay {unc.delay[0]:g}..{unc.delay[1]:g} s, "
              f"tilt +-{unc.tilt:g} rad")
    from host.studies.sweep import SweepInterrupted

    try:
        if args.kind == "hil":
            from host.cli.sweep_hil import run_hil_mc

            return run_hil_mc(args, params, unc, out, bar, write_table, _fmt_table)
        if args.kind == "robustness":
            return _robustness(args, base, out, bar)
        if args.kind == "tune":
            return _tune(args, base, out, bar)
        return _tilt(args, params, out, bar, noise, plant)
    except SweepInterrupted as exc:
        _write_partial(args, exc, out)
        raise


def _write_partial(args: argparse.Namespace, exc: Any, out: Path) -> None:
    """After Ctrl-C: the finished runs as CSV + Parquet and a summary marked partial."""
    from host.studies.sweep import summarise

    sys.stderr.write("\n")
    stem = {"robustness": "robustness", "tune": "tune_runs", "tilt": "tilt_runs", "hil": "hil_mc"}[args.kind]
    table = exc.table
    files = write_table(table, out / stem) if table else []
    summary: dict[str, Any] = {"partial": True, "kind": args.kind, "runs_done": exc.runs_done,
                               "runs_planned": exc.runs_total, "seed": args.seed}
    if table and args.kind == "robustness":
        summary.update(summarise(table))
    path = out / f"{args.kind}_summary.json"
    path.write_text(json.dumps(summary, indent=2, default=float))
    files.append(path)
    print(f"interrupted: {exc.runs_done} of {exc.runs_total} runs finished; partial results: "
          + ", ".join(str(f) for f in files), file=sys.stderr)


def _ranges(args: argparse.Namespace) -> Any:
    """The Monte Carlo ranges: the defaults, the ``--ranges`` file's keys, then ``--tilt0``."""
    from host.studies.ranges import RangesError, load_ranges
    from host.studies.sweep import Uncertainty

    unc = Uncertainty()
    if args.ranges is not None:
        if args.kind not in ("robustness", "hil"):
            raise A.UsageError(f"--ranges applies to robustness and hil, not {args.kind}")
        try:
            unc = load_ranges(args.ranges)
        except RangesError as exc:
            raise A.UsageError(f"bad ranges file: {exc}") from None
    if args.tilt0 is not None:
        from dataclasses import replace

        if args.ranges is not None and unc.tilt != Uncertainty().tilt:
            print(f"--tilt0 {args.tilt0:g} replaces the ranges file's tilt {unc.tilt:g}")
        unc = replace(unc, tilt=args.tilt0)
    return unc


def _custom(args: argparse.Namespace) -> bool:
    return args.q_x is not None or args.q_phi is not None or args.r is not None or args.observer is not None


def _chosen_design(args: argparse.Namespace) -> Any:
    """The design given by --q-x/--q-phi/--r/--observer/--u-max (default: the shipped design).

    Unchanged weights keep the shipped design's values (``host.design.discrete.Q_DEFAULT``,
    including its speed weights).
    """
    from host.design.discrete import OBSERVER_DEFAULT, Q_DEFAULT, R_DEFAULT
    from host.studies.sweep import Design

    if args.observer is not None and not args.observer > 0:
        raise A.UsageError(f"--observer must be > 0, got {args.observer}")
    if not _custom(args):
        return Design("lqr", u_max=args.u_max)
    qx = Q_DEFAULT[0] if args.q_x is None else args.q_x
    qphi = Q_DEFAULT[2] if args.q_phi is None else args.q_phi
    r = R_DEFAULT if args.r is None else args.r
    obs = OBSERVER_DEFAULT if args.observer is None else args.observer
    return Design(f"qx{qx:g}_qphi{qphi:g}_r{r:g}_obs{obs:g}", Q=(qx, Q_DEFAULT[1], qphi, Q_DEFAULT[3]), R=r,
                  observer=obs, u_max=args.u_max)


def _robustness(args: argparse.Namespace, cfg: Any, out: Path, bar: ProgressBar) -> int:
    from host.studies.sweep import robustness, summarise, worst_case_scenarios, write_scenarios

    n = args.n or 1000
    t0 = time.perf_counter()
    table = robustness(cfg, n, chunk=args.chunk, scheduler=args.scheduler, progress=bar)
    wall = time.perf_counter() - t0
    s = summarise(table)
    p = cfg.params
    files = write_table(table, out / "robustness")
    summary = {"runs": n, "seed": args.seed, "wall_s": wall, **s}
    (out / "robustness_summary.json").write_text(json.dumps(summary, indent=2))
    print(f"{n} runs of {cfg.duration:g} s in {wall:.1f} s")
    print(f"success {s['success_rate']:.1%}  (|phi| < {p.phi_max:g} rad: {s['ok_phi_rate']:.1%}, "
          f"settle < {p.t_settle:g} s: {s['ok_settle_rate']:.1%}, |xddot| <= {p.a_max:g} m/s^2: {s['ok_accel_rate']:.1%}, "
          f"fallen: {s['fallen_rate']:.1%})")
    rows = [{"metric": k, "p5": s[f"{k}_p5"], "median": s[f"{k}_p50"], "p95": s[f"{k}_p95"], "max": s[f"{k}_max"]}
            for k in ("phi_max", "settle", "xddot_max", "force_max", "x_max", "phi_rms", "force_rms")]
    print(_fmt_table(rows, ("metric", "p5", "median", "p95", "max")))
    scen = worst_case_scenarios(cfg, table, args.worst)
    paths = write_scenarios(scen, str(out / "scenarios"))
    for sc, path in zip(scen, paths):
        print(f"worst: {path}  ({sc.expect.note})")
    if not args.no_plots:
        files.append(_plot_robustness(table, p, out / "robustness.png"))
    print("wrote " + ", ".join(str(f) for f in files))
    return 0


def _designs(args: argparse.Namespace) -> list[Any]:
    from dataclasses import replace

    from host.studies.sweep import design_grid, design_random

    ds = design_grid() if args.search == "grid" else design_random(args.designs, args.seed)
    return [replace(d, u_max=args.u_max) for d in ds]


def _tune(args: argparse.Namespace, cfg: Any, out: Path, bar: ProgressBar) -> int:
    from host.studies.sweep import tune

    n = args.n or 100
    designs = _designs(args)
    t0 = time.perf_counter()
    rows, table = tune(cfg, designs, n, chunk=args.chunk, scheduler=args.scheduler, progress=bar)
    wall = time.perf_counter() - t0
    print(f"{len(designs)} designs x {n} runs in {wall:.1f} s (same seeds for every design)")
    cols = ("design", "success_rate", "settle_p50", "force_max_p50", "phi_rms_p50", "xddot_max_p95", "pareto")
    front = [r for r in rows if r.get("pareto")]
    print("Pareto front (settling time vs peak force vs noise RMS of phi, medians over the runs):")
    print(_fmt_table(front, cols))
    bad = [r for r in rows if r.get("error")]
    if bad:
        print(f"{len(bad)} designs rejected by the design code (see tune_designs.csv)")
    files = write_table(_rows_to_cols(rows), out / "tune_designs")
    files += write_table(table, out / "tune_runs")
    if not args.no_plots:
        files.append(_plot_tune(rows, out / "tune.png"))
    print("wrote " + ", ".join(str(f) for f in files))
    return 0


def _tilt(args: argparse.Namespace, params: Any, out: Path, bar: ProgressBar, noise: Any, plant: Any = None) -> int:
    from dataclasses import replace

    from host.studies.sweep import default_tilt_designs, tilt

    if not args.step > 0:
        raise A.UsageError(f"--step must be > 0, got {args.step}")
    if _custom(args):
        designs = [_chosen_design(args)]
    else:
        designs = [replace(d, u_max=args.u_max) if args.u_max is not None else d for d in default_tilt_designs(params)]
    rows, table = tilt(params, designs, step=args.step, duration=args.duration, noise=noise, drive=args.drive,
                       seed=args.seed, chunk=args.chunk, scheduler=args.scheduler, progress=bar, plant=plant)
    print(f"largest recoverable initial tilt, cart acceleration limited to {params.a_max:g} m/s^2 "
          f"(physical limit atan(a_max/g) = {rows[0]['physical_limit']:.4f} rad = {rows[0]['physical_limit_deg']:.1f} deg):")
    print(_fmt_table(rows, ("design", "tilt_max", "tilt_max_deg", "tilt_max_track", "physical_limit", "physical_limit_deg")))
    files = write_table(_rows_to_cols(rows), out / "tilt")
    files += write_table(table, out / "tilt_runs")
    if not args.no_plots:
        files.append(_plot_tilt(rows, out / "tilt.png"))
    print("wrote " + ", ".join(str(f) for f in files))
    return 0


# ------------------------------------------------------------------ plots
def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _plot_robustness(t: Mapping[str, np.ndarray], p: Any, path: Path) -> Path:
    plt = _plt()
    panels = [("phi_max", "peak |phi| (rad)", p.phi_max), ("settle", "settling time (s)", p.t_settle),
              ("xddot_max", "peak |xddot| (m/s^2)", p.a_max), ("force_max", "peak force (N)", None),
              ("phi_rms", "phi RMS, final 1 s (rad)", None), ("x_max", "peak |x| (m)", p.track)]
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5))
    for ax, (k, label, lim) in zip(axes.ravel(), panels):
        v = np.asarray(t[k], dtype=float)
        v = v[np.isfinite(v)]
        ax.hist(v, bins=40, color="tab:blue", alpha=0.8)
        if lim is not None:
            ax.axvline(lim, color="tab:red", ls="--", label="constraint")
            ax.legend(fontsize=8)
        ax.set_xlabel(label)
        ax.set_ylabel("runs")
    fig.suptitle(f"robustness: {len(t['run'])} runs, success {np.mean(t['success']):.1%}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _plot_tune(rows: Sequence[Mapping[str, Any]], path: Path) -> Path:
    plt = _plt()
    ok = [r for r in rows if not r.get("error")]
    fig, ax = plt.subplots(figsize=(8, 5.5))
    x = [r["settle_p50"] for r in ok]
    y = [r["force_max_p50"] for r in ok]
    c = [r["phi_rms_p50"] for r in ok]
    sc = ax.scatter(x, y, c=c, s=[20 + 80 * r["success_rate"] for r in ok], cmap="viridis")
    fr = [r for r in ok if r["pareto"]]
    ax.scatter([r["settle_p50"] for r in fr], [r["force_max_p50"] for r in fr], facecolors="none", edgecolors="red",
               s=160, label="Pareto front")
    fig.colorbar(sc, ax=ax, label="phi RMS (rad), median")
    ax.set_xlabel("settling time (s), median")
    ax.set_ylabel("peak force (N), median")
    ax.set_yscale("log")
    ax.legend()
    ax.set_title("tune: LQR weights x observer speed (marker size = success rate)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _plot_tilt(rows: Sequence[Mapping[str, Any]], path: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    names = [r["design"] for r in rows]
    ax.bar(names, [r["tilt_max_deg"] for r in rows], color="tab:blue", label="recovered (simulation)")
    ax.axhline(rows[0]["physical_limit_deg"], color="tab:red", ls="--", label="atan(a_max/g)")
    ax.set_ylabel("largest recoverable initial tilt (deg)")
    ax.legend()
    ax.tick_params(axis="x", rotation=20)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
