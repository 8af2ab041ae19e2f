"""``upright demo`` (``make demo``): the report's scenarios balanced by the real firmware.

Starts the firmware under the MicroPython unix port on a virtual serial port (a pty),
closes the loop with the simulated robot for every scenario of the design report (lockstep,
serial link), compares each run with the float design in pure simulation, prints the
summary table with PASS/FAIL per constraint, and writes per scenario a CSV log, a PNG of
the signals and an animated GIF of the cart and pendulum -- plus ``index.html`` showing
them all under the summary table (the text table's checks with its marks: ``*`` an expected and
documented FAIL, ``!`` an unexpected outcome; ``n/a`` with its reason where a run has no float
comparison) -- under ``<out>/demo``.  A short design summary comes first when the design
module is available (``--no-design`` skips it).
"""

from __future__ import annotations

import argparse
import html
import math
import sys
from pathlib import Path
from typing import Any, Sequence

from host.cli.args import nonempty

__all__ = ["add_arguments", "run", "design_summary", "write_index", "summary_html", "TOLERANCE"]


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


TOLERANCE = 0.01
"""Largest ``|phi_hil - phi_float|`` (rad) the demo accepts (the text table's and the page's '!')."""

_CSS = ("body{font-family:sans-serif;margin:1.5em;max-width:1400px}"
        "table{border-collapse:collapse;font-size:14px}th,td{padding:3px 8px;border-bottom:1px solid #ddd}"
        "td.n{text-align:right;font-variant-numeric:tabular-nums}th{background:#f3f3f3}"
        ".PASS{color:#1e7b34}.FAIL{color:#b3261e}.NA{color:#777}.unexpected{background:#fde0dc;font-weight:bold}"
        "p.notes{font-size:13px;color:#333;max-width:1100px}")


def _num(v: float, fmt: str, suffix: str = "") -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt) + suffix


def _mark(c: Any) -> str:
    # as the text table (sim.metrics.summary_table): '!' not as the scenario expects, '*' an
    # expected and documented FAIL
    return "!" if not c.as_expected else ("*" if c.status == "FAIL" else "")


def _phi_cell(r: Any, tolerance: float) -> tuple[str, str, bool]:
    """(text, title, as expected) of a run's ``|phi_hil - phi_float|``."""
    err = r.phi_error()
    if math.isnan(err):
        why = r.phi_error_note() or "no comparison"
        return "n/a", why, True
    ok = err <= tolerance
    return f"{err:.4f}" + ("" if ok else "!"), f"tolerance {tolerance:g} rad", ok


def summary_html(runs: Sequence[Any], tolerance: float = TOLERANCE) -> str:
    """The summary table of the runs as HTML: the text table's metrics and checks, with its marks
    (``*`` expected and documented, ``!`` unexpected), ``|phi_hil - phi_float|`` (``n/a`` with
    the reason where there is no comparison), and the notes under it."""
    summaries = [r.summary() for r in runs]
    labels: list[str] = []
    for sm in summaries:
        for c in sm.checks:
            if c.label not in labels:
                labels.append(c.label)
    e = html.escape
    head = ["scenario", "|phi|max (rad)", "settle (s)", "overshoot", "|a|max (m/s²)", "|F|max (N)", "sat (s)",
            "phi rms (rad)", "x err (m)", *labels, "|phi_hil - phi_float| (rad)"]
    rows = []
    notes: list[str] = []
    nas: list[str] = []
    n_fail = n_expected = n_unexp = 0
    for r, sm in zip(runs, summaries):
        m = sm.metrics
        cells = [f'<td><a href="#{e(r.name)}">{e(r.name)}</a></td>']
        for v, fmt, suf in ((m.peak_phi, ".4f", ""), (m.settling_time, ".2f", ""), (m.overshoot, ".0f", "%"),
                            (m.peak_xddot, ".2f", ""), (m.peak_force, ".1f", ""), (m.time_saturated, ".2f", ""),
                            (m.rms_phi, ".4f", ""), (m.ss_cart_error, ".4f", "")):
            cells.append(f'<td class="n">{_num(v, fmt, suf)}</td>')
        by = {c.label: c for c in sm.checks}
        for lab in labels:
            c = by.get(lab)
            if c is None:
                cells.append("<td></td>")
                continue
            mark = _mark(c)
            n_fail += c.status == "FAIL"
            n_expected += mark == "*"
            n_unexp += mark == "!"
            cls = "NA" if c.status == "N/A" else c.status
            title = f"{c.value:.3g} {c.unit} vs {c.limit:g} {c.unit}; expected: {c.expected}".replace("nan ", "- ")
            cells.append(f'<td class="{cls}{" unexpected" if mark == "!" else ""}" title="{e(title)}">'
                         f"{e(c.status + mark)}</td>")
        text, title, ok = _phi_cell(r, tolerance)
        if not ok:
            n_unexp += 1
        if text == "n/a":
            nas.append(f"{r.name}: {title}")
            text = "n/a&#8224;"
        cells.append(f'<td class="n{"" if ok else " unexpected"}" title="{e(title)}">{text}</td>')
        rows.append("<tr>" + "".join(cells) + "</tr>")
        if sm.note and not sm.passed:
            notes.append(f"<b>{e(r.name)}</b>: {e(sm.note)}")
    foot = (f"<p>{len(runs)} runs, {n_fail} constraint FAIL(s) ({n_expected} expected and documented, marked *), "
            f"{n_unexp} unexpected outcome(s) (marked !).</p>")
    parts = ['<table id="summary"><tr>' + "".join(f"<th>{e(h)}</th>" for h in head) + "</tr>",
             *rows, "</table>", foot]
    if notes:
        parts.append('<p class="notes">* expected and documented (each scenario\'s note; the report\'s scenarios in '
                     "docs/parameters.md): " + "; ".join(notes) + "</p>")
    if nas:
        parts.append('<p class="notes">&#8224; no comparison with the float design: '
                     + "; ".join(e(t) for t in nas) + "</p>")
    return "\n".join(parts)


def write_index(runs: Sequence[Any], out: Path, tolerance: float = TOLERANCE, *, partial: str | None = None) -> Path:
    """An ``index.html``: the summary table (:func:`summary_html`), then every run's PNG and GIF
    with its checks (``partial``: a line saying the run was interrupted)."""
    e = html.escape
    sections = []
    for r in runs:
        s = r.summary()
        checks = ", ".join(f"{e(c.label)}: {e(c.status + _mark(c))}" for c in s.checks)
        text, title, _ = _phi_cell(r, tolerance)
        phi = f"{text} ({e(title)})" if text == "n/a" else f"{text} rad"
        files = r.stats.get("files", {})
        imgs = "".join(
            f'<img src="{e(Path(files[k]).name)}" style="max-width:48%;vertical-align:top">'
            for k in ("gif", "png") if k in files
        )
        sections.append(f'<h2 id="{e(r.name)}">{e(r.name)}</h2><p>{e(r.scenario.description)}<br>{checks}; '
                        f"|phi_hil - phi_float| = {phi}</p>{imgs}")
    title = runs[0].link if runs else "serial"
    page = ("<!doctype html><meta charset='utf-8'><title>upright demo</title>"
            f"<style>{_CSS}</style>"
            "<h1>upright: the firmware balancing the simulated pendulum</h1>"
            + (f"<p><b>{e(partial)}</b></p>" if partial else "")
            + "<p>Each run: the real firmware (MicroPython, fixed point) in the loop with the simulated robot "
            f"over a virtual serial port ({e(title)} link); dashed lines are the float design in pure simulation.</p>"
            "<h2>Summary: the report's constraints</h2>" + summary_html(runs, tolerance)
            + "\n" + "\n".join(sections))
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
            report(done, tolerance=TOLERANCE, out=out)
            write_index(done, out, TOLERANCE,
                        partial=f"PARTIAL: interrupted after {len(done)} of {len(scenarios)} scenario(s)")
        path = write_summary(done, out, planned=scenarios, tolerance=TOLERANCE, interrupted=True)
        print(f"interrupted: {len(done)} of {len(scenarios)} scenario(s) finished; partial summary: {path}",
              file=sys.stderr)
        raise KeyboardInterrupt from None
    status = report(runs, tolerance=TOLERANCE, out=out)
    write_summary(runs, out, planned=scenarios, tolerance=TOLERANCE)
    index = write_index(runs, out, TOLERANCE)
    print(f"Open {index.resolve()} in a browser to see every run (plots and animations).")
    if status:
        # the demo shows what happens; `make test` is where a difference fails the build
        print("(the demo finished; the runs marked '!' above differ from the report's expectations)")
    return 0
