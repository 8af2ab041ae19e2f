"""``upright demo`` (``make demo``): the report's scenarios balanced by the real firmware.

Starts the firmware under the MicroPython unix port on a virtual serial port (a pty),
closes the loop with the simulated robot for every scenario of the design report (lockstep,
serial link), compares each run with the float design in pure simulation, prints the
summary table with PASS/FAIL per constraint, and writes per scenario a CSV log, a PNG of
the signals and an animated GIF of the cart and pendulum -- plus ``index.html`` showing
them all -- under ``<out>/demo``.  A short design summary comes first when the design
module is available (``--no-design`` skips it).
"""

from __future__ import annotations

import argparse
import html
import sys
from pathlib import Path
from typing import Any, Sequence

from host.cli.args import nonempty

__all__ = ["add_arguments", "run", "design_summary", "write_index"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright demo``."""
    parser.add_argument("--out", default="out", metavar="DIR", help="output root; files go to DIR/demo (default out)")
    parser.add_argument("--link", choices=("serial", "can"), default="serial", help="framing (default serial)")
    parser.add_argument("--scenario", default="all", metavar="NAME", type=nonempty,
                        help="scenario name(s) comma-separated, a TOML path, or 'all' (the report's; default)")
    parser.add_argument("--no-design", action="store_true", help="skip the design summary")
    parser.add_argument("--no-gif", action="store_true", help="skip the animated GIFs (faster)")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    from host.cli.plant import add_plant_argument

    add_plant_argument(parser)


def design_summary() -> str | None:
    """The state-feedback part of the lead's design report, or ``None`` if unavailable."""
    try:
        from host.cli.design import build_report
        from sim.params import load_params

        text, _ = build_report(load_params(), search=False)
    except Exception:  # noqa: BLE001 - optional: the demo runs without it
        return None
    lines = text.splitlines()
    start = next((i for i, s in enumerate(lines) if s.startswith("State feedback")), None)
    if start is None:
        return None
    end = next((i for i in range(start, len(lines)) if lines[i].startswith("Observer poles")), start + 8)
    return "\n".join(lines[start:end + 1])


def write_index(runs: Sequence[Any], out: Path) -> Path:
    """An ``index.html`` showing every run's PNG and GIF with its checks."""
    rows = []
    for r in runs:
        s = r.summary()
        checks = ", ".join(f"{html.escape(c.label)}: {c.status}" for c in s.checks)
        files = r.stats.get("files", {})
        imgs = "".join(
            f'<img src="{html.escape(Path(files[k]).name)}" style="max-width:48%;vertical-align:top">'
            for k in ("gif", "png") if k in files
        )
        rows.append(f"<h2>{html.escape(r.name)}</h2><p>{html.escape(r.scenario.description)}<br>{checks}; "
                    f"|phi_hil - phi_float| = {r.phi_error():.4f} rad</p>{imgs}")
    page = ("<!doctype html><meta charset='utf-8'><title>upright demo</title>"
            "<h1>upright: the firmware balancing the simulated pendulum</h1>"
            "<p>Each run: the real firmware (MicroPython, fixed point) in the loop with the simulated robot "
            "over a virtual serial port; dashed lines are the float design in pure simulation.</p>"
            + "\n".join(rows))
    path = out / "index.html"
    path.write_text(page)
    return path


def run(args: argparse.Namespace) -> int:
    """Run ``upright demo``."""
    from host.boards.vport import PortError
    from host.cli.args import check_out_dir
    from host.cli.hil import Progress, check_scenarios, report, write_summary
    from host.cli.main import interrupted
    from host.hil import runs as hil_runs
    from host.hil.errors import HilError

    out = check_out_dir(Path(args.out) / "demo", "--out")
    scenarios = hil_runs.resolve_scenarios(args.scenario)
    from host.cli.plant import load_plant, print_precedence
    from sim.params import load_params

    plant = load_plant(getattr(args, "plant", None), load_params())
    check_scenarios(scenarios, plant)
    print_precedence(scenarios, plant)
    if not args.no_design:
        summ = design_summary()
        if summ:
            print("Design (from `upright design`):\n" + summ + "\n")
    if not args.quiet:
        print(f"Running {len(scenarios)} scenario(s) of the design report with the firmware in the loop "
              f"(MicroPython unix port on a virtual serial port, {args.link} link, lockstep)...", file=sys.stderr)
    done: list[Any] = []
    try:
        runs = hil_runs.run_scenarios(scenarios, link=args.link, mode="lockstep", out=out, compare=True,
                                      gif=not args.no_gif, progress=Progress(enabled=not args.quiet),
                                      on_result=done.append, plant=plant)
    except (PortError, HilError, KeyboardInterrupt) as exc:
        if not isinstance(exc, KeyboardInterrupt) and not interrupted():
            print(f"upright demo: {exc}", file=sys.stderr)
            return 1
        sys.stderr.write("\n")
        if done:
            report(done, out=out)
            write_index(done, out)
        path = write_summary(done, out, planned=scenarios, interrupted=True)
        print(f"interrupted: {len(done)} of {len(scenarios)} scenario(s) finished; partial summary: {path}",
              file=sys.stderr)
        raise KeyboardInterrupt from None
    status = report(runs, out=out)
    write_summary(runs, out, planned=scenarios)
    index = write_index(runs, out)
    print(f"Open {index.resolve()} in a browser to see every run (plots and animations).")
    if status:
        # the demo shows what happens; `make test` is where a difference fails the build
        print("(the demo finished; the runs marked '!' above differ from the report's expectations)")
    return 0
