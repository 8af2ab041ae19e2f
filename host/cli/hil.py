"""``upright hil``: the firmware balancing the simulated pendulum, over a serial or CAN link.

Examples
--------
The report's scenarios, firmware under the MicroPython unix port on a virtual serial port::

    upright hil --virtual --scenario all --out out/hil

One scenario in real time over CAN frames (python-can ``serial`` interface on the pty)::

    upright hil --virtual --link can --mode realtime --scenario tilt_0p1

A board flashed with ``make flash`` (the one bundle runs the robot and serves HIL): the command
sends ``mode hil`` over the board's link (its lockstep HIL main takes the same UART, no reflash),
runs the scenarios and sends ``mode robot`` at the end::

    upright hil --port /dev/ttyUSB0 --scenario tilt_0p3

It waits up to ``--answer-timeout`` (10 s) for the board's first answer, then measures the
board's clock against the wall's and waits 2 s per answer scaled by it (an emulated Pico, the
virtual robot of ``upright emulate rp2040 --pty``, runs at 0.05-0.4x real time); ``--timeout``
fixes the answer time instead.

Writes ``<out>/<scenario>.csv``, ``.png`` and ``.gif`` per scenario and prints a summary
table with PASS/FAIL per constraint; the exit status is 1 if a check came out differently
from the scenario's ``[expect]`` or the HIL run left the float pure simulation by more
than ``--tolerance`` rad of tilt.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any, Sequence, TextIO

from host.cli import args as A

__all__ = ["add_arguments", "run", "report", "Progress", "Plan", "STEP_NOTE"]

#: what the ``fw step us`` column measures (printed under the table)
STEP_NOTE = ("fw step us: mean time of one firmware control step as the board timed it (telemetry step_us). "
             "In lockstep the host paces the ticks and no period applies, so it is not a load figure: a board in "
             "HIL mode runs the general step with the HIL sensor path, not the robot's fast tick -- a mean near "
             "the period (2000 us at 500 Hz) is not a 100 % load. The robot's own tick against its period: "
             "`upright hil --emulate rp2040` (cost per tick in emulated cycles).")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright hil``."""
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--virtual", action="store_true",
                       help="run the firmware under the MicroPython unix port on a pty (default)")
    where.add_argument("--port", metavar="DEV",
                       help="a board flashed with `make flash` (switched to HIL mode and back) or running "
                            "firmware.main_hil: serial device, or CAN channel with --link can")
    where.add_argument("--emulate", choices=("rp2040",), metavar="BOARD",
                       help="rp2040: the board firmware (main.py) on an emulated Pico, the plant on its pins")
    parser.add_argument("--link", choices=("serial", "can"), default="serial",
                        help="framing: COBS serial frames or CAN frames (default serial)")
    parser.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep",
                        help="lockstep: deterministic, as fast as the link; realtime: the firmware paces itself")
    parser.add_argument("--scenario", default="all", metavar="NAME", type=A.nonempty,
                        help="scenario name(s) comma-separated, a TOML path, or 'all' (the report's; default)")
    parser.add_argument("--out", default="out/hil", metavar="DIR", help="output directory (default out/hil)")
    parser.add_argument("--can-interface", type=A.can_interface, default="slcan", metavar="NAME",
                        help="python-can interface for --port with --link can (default slcan)")
    parser.add_argument("--node", type=A.int_range(0, 63), default=1, help="CAN node id of the board (default 1)")
    parser.add_argument("--baudrate", "--baud", dest="baudrate", type=A.positive_int, default=A.board_baud(),
                        help=f"serial line rate for --port (default {A.board_baud()}: firmware/board.py UART_BAUD)")
    parser.add_argument("--timeout", type=A.in_range(0.1, 600), default=None, metavar="S",
                        help="--port: seconds (wall) to wait for any one answer of the board (default: 2 s scaled by "
                             "the board's clock, measured against the wall's at the start: an emulated board, "
                             "slower than real time, gets longer)")
    parser.add_argument("--answer-timeout", type=A.in_range(0.1, 600), default=10.0, metavar="S",
                        help="--port: seconds (wall) for the board to answer at all (default 10)")
    parser.add_argument("--no-gif", action="store_true", help="skip the animated GIFs (faster)")
    parser.add_argument("--no-plots", action="store_true", help="skip PNG and GIF")
    parser.add_argument("--no-compare", action="store_true", help="skip the float pure-simulation comparison")
    parser.add_argument("--tolerance", type=A.positive, default=0.01,
                        help="largest |phi_hil - phi_float| accepted (rad, default 0.01)")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    parser.add_argument("--json", metavar="FILE",
                        help="also write one JSON object per scenario (verdict, metrics, loop tick time)")
    from host.cli.plant import add_plant_argument

    add_plant_argument(parser)


class Progress:
    """Progress of long runs on a terminal line (``\\r``), or a line per quarter when piped."""

    def __init__(self, stream: TextIO | None = None, enabled: bool = True) -> None:
        # resolved at call time: a default bound at import would outlive a replaced sys.stderr
        stream = sys.stderr if stream is None else stream
        self.stream = stream
        self.enabled = enabled
        self.tty = bool(getattr(stream, "isatty", lambda: False)())
        self._last: dict[str, int] = {}
        self._t0 = time.perf_counter()

    def __call__(self, name: str, k: int, n: int) -> None:
        if not self.enabled or n <= 0:
            return
        if k == 0:
            self._t0 = time.perf_counter()
        pct = int(100 * k / n)
        if self.tty:
            width = 30
            fill = int(width * k / n)
            el = time.perf_counter() - self._t0
            self.stream.write(f"\r  {name:28s} [{'#' * fill}{'.' * (width - fill)}] {pct:3d}% {el:5.1f}s")
            if k >= n:
                self.stream.write("\n")
            self.stream.flush()
            return
        q = pct // 25
        if self._last.get(name, -1) != q:
            self._last[name] = q
            self.stream.write(f"  {name}: {pct}% ({k}/{n} ticks)\n")
            self.stream.flush()


class Plan:
    """The whole run's progress: an estimate up front, ``[i/N]`` per scenario, time left.

    Parameters
    ----------
    scenarios : sequence of Scenario
        What will run, in order.
    rate : float
        Control ticks per second of robot time.
    stream : text stream, optional
        Default: the current ``sys.stderr``.
    enabled : bool
        False: silent.
    """

    def __init__(self, scenarios: Sequence[Any], rate: float, stream: TextIO | None = None,
                 enabled: bool = True) -> None:
        self.stream = sys.stderr if stream is None else stream
        self.enabled = enabled
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.names = [sc.name for sc in scenarios]
        self.ticks = {sc.name: int(round(sc.duration * rate)) for sc in scenarios}
        self.robot_s = float(sum(sc.duration for sc in scenarios))
        self.total = sum(self.ticks.values())
        self.done = 0  # ticks of the finished scenarios
        self._current: str | None = None
        self._last_n = 0
        self._t0: float | None = None
        self._q: dict[str, int] = {}
        self._estimated = False

    def header(self) -> str:
        """The line printed before the board starts."""
        n = len(self.names)
        return (f"{n} scenario(s), {self.robot_s:g} s of robot time ({self.total:,} control ticks); the time they "
                "take depends on the link and board -- estimated once the first ticks are measured")

    def _write(self, text: str) -> None:
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):
            pass

    def left_s(self, k: int) -> float | None:
        """Seconds left for the whole run at the tick rate measured so far (None: too early)."""
        if self._t0 is None:
            return None
        el = time.perf_counter() - self._t0
        got = self.done + k
        if got < 50 or el < 1.0:
            return None
        return (self.total - got) * el / got

    def __call__(self, name: str, k: int, n: int) -> None:
        if not self.enabled or n <= 0:
            return
        if self._t0 is None:
            self._t0 = time.perf_counter()
        if name != self._current:
            if self._current is not None:
                self.done += self._last_n
            self._current = name
            i = self.names.index(name) + 1 if name in self.names else 0
            if not self.tty:
                self._write(f"  [{i}/{len(self.names)}] {name}: {n} ticks\n")
        self._last_n = n
        i = self.names.index(name) + 1 if name in self.names else 0
        left = self.left_s(k)
        if left is not None and not self._estimated:
            self._estimated = True
            el = time.perf_counter() - self._t0
            rate = (self.done + k) / el
            self._write(("\n" if self.tty else "") + f"  estimate: {_mmss(el + left)} in all at {rate:.0f} ticks/s "
                        f"({_mmss(left)} left)\n")
        eta = f", ~{_mmss(left)} left" if left is not None else ""
        pct = int(100 * k / n)
        if self.tty:
            width = 24
            fill = int(width * k / n)
            self._write(f"\r  [{i}/{len(self.names)}] {name:24s} [{'#' * fill}{'.' * (width - fill)}] {pct:3d}%{eta}   ")
            if k >= n:
                self._write("\n")
            return
        q = pct // 25
        if self._q.get(name, -1) != q:
            self._q[name] = q
            self._write(f"  [{i}/{len(self.names)}] {name}: {pct}% ({k}/{n} ticks){eta}\n")


def _mmss(s: float) -> str:
    s = max(0.0, s)
    if s < 90:
        return f"{s:.0f} s"
    m, sec = divmod(int(round(s)), 60)
    return f"{m} min {sec:02d} s"


def report(runs: Sequence[Any], *, tolerance: float = 0.01, out: str | Path | None = None,
           stream: TextIO | None = None, title: str | None = None) -> int:
    """Print the summary table and the loop figures of HIL runs; return the exit status.

    Parameters
    ----------
    runs : sequence of host.hil.session.HilRun
        The runs.
    tolerance : float
        Largest accepted ``|phi_hil - phi_float|`` (rad) when a float reference is present.
    out : str or Path, optional
        Where the files were written (printed).
    stream : text stream, optional
        Where to print (default: the current ``sys.stdout``).
    title : str, optional
        Table title.

    Returns
    -------
    int
        0 if every check came out as the scenario expects and every compared run agrees
        with the float simulation; 1 otherwise.
    """
    from sim.metrics import summary_table

    stream = sys.stdout if stream is None else stream
    summaries = [r.summary() for r in runs]
    if runs and title is None:
        r0 = runs[0]
        title = f"Firmware in the loop ({r0.link} link, {r0.mode}): the report's constraints"
    print(summary_table(summaries, title=title), file=stream)
    print("", file=stream)
    head = f"  {'scenario':28s} {'ticks':>6s} {'x real time':>11s} {'|dphi| vs float':>15s} {'fw step us':>10s}"
    rt = any(r.mode == "realtime" for r in runs)
    if rt:
        head += (f" {'latency us (mean/p99/max)':>26s} {'late':>5s} {'fw overruns':>11s} {'fw period max':>13s}"
                 f" {'steal ms':>8s}")
    print(head, file=stream)
    bad = 0
    for r, s in zip(runs, summaries):
        err = r.phi_error()
        ok_err = math.isnan(err) or err <= tolerance
        if not s.as_expected or not ok_err:
            bad += 1
        st = r.stats
        line = (f"  {r.name:28s} {st.get('ticks', 0):6d} {r.realtime_factor:10.1f}x "
                f"{'-' if math.isnan(err) else format(err, '.4f'):>14s}{' ' if ok_err else '!'} "
                f"{st.get('fw_step_us_mean', math.nan):10.1f}")
        if rt:
            line += (f" {st.get('latency_us_mean', math.nan):8.0f}/{st.get('latency_us_p99', math.nan):6.0f}/"
                     f"{st.get('latency_us_max', math.nan):7.0f}   {st.get('late', 0):5d} "
                     f"{st.get('fw_overruns', -1):11d} {st.get('fw_period_max_us', -1):10d} us"
                     f" {st.get('steal_s', math.nan) * 1e3:8.0f}")
        print(line, file=stream)
        if st.get("gains", "firmware default") != "firmware default":
            print(f"  {'':28s} (gain table uploaded: {st['gains']})", file=stream)
    import textwrap

    if any(r.mode == "lockstep" for r in runs):
        print("\n" + textwrap.fill(STEP_NOTE, width=100, initial_indent="  ", subsequent_indent="  "), file=stream)
    if out is not None:
        print(f"\nCSV logs, PNG plots and GIF animations: {Path(out).resolve()}", file=stream)
    if bad:
        print(f"\n{bad} run(s) not as expected (see '!' marks).", file=stream)
    return 1 if bad else 0


def write_summary(runs: Sequence[Any], out: Path, *, planned: Sequence[Any], tolerance: float = 0.01,
                  interrupted: bool = False) -> Path:
    """Write ``<out>/summary.txt``: the summary table of the finished runs, marked partial when
    the run was interrupted (and listing the scenarios that did not finish)."""
    import io

    buf = io.StringIO()
    done = {r.name for r in runs}
    if interrupted:
        left = [s.name for s in planned if s.name not in done]
        buf.write(f"PARTIAL: interrupted after {len(runs)} of {len(planned)} scenario(s); "
                  f"not finished: {', '.join(left) or '-'}\n\n")
    if runs:
        report(runs, tolerance=tolerance, out=out, stream=buf)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "summary.txt"
    path.write_text(buf.getvalue())
    return path


def check_scenarios(scenarios: Sequence[Any], params: Any = None) -> None:
    """Refuse (before the board starts) a scenario list that is empty or does not fit the robot."""
    from sim.params import load_params

    if not scenarios:
        raise A.UsageError("--scenario: no scenario named")
    params = params or load_params()
    for sc in scenarios:
        sc.check(params)


def run(args: argparse.Namespace) -> int:
    """Run ``upright hil``."""
    from host.boards.vport import PortError
    from host.cli.main import interrupted
    from host.hil import runs as hil_runs
    from host.hil.errors import HilError

    out = A.check_out_dir(args.out, "--out")
    json_path = A.check_out_file(args.json, "--json")
    scenarios = hil_runs.resolve_scenarios(args.scenario)
    from host.cli.plant import load_plant, print_precedence
    from sim.params import load_params

    plant = load_plant(getattr(args, "plant", None), load_params())
    check_scenarios(scenarios, plant)
    print_precedence(scenarios, plant)
    prog = Progress(enabled=not args.quiet)
    if args.emulate:
        from host.cli.emulate import hil_emulated

        return hil_emulated(args, out, scenarios, prog, json_path, cli=sys.modules[__name__], plant=plant)
    where = "virtual board (MicroPython unix port on a pty)" if args.port is None else args.port
    plan = Plan(scenarios, float((plant or load_params()).values["loop.rate"]), enabled=not args.quiet)
    prog = plan  # type: ignore[assignment]
    if not args.quiet:
        print(f"upright hil: {args.link} link, {args.mode}, {where}: {plan.header()}", file=sys.stderr)
    done: list[Any] = []
    try:
        runs = hil_runs.run_scenarios(
            scenarios, port=args.port, link=args.link, mode=args.mode, out=out,
            compare=not args.no_compare, gif=not (args.no_gif or args.no_plots), plot=not args.no_plots,
            progress=prog, node=args.node, baudrate=args.baudrate, can_interface=args.can_interface,
            on_result=done.append, plant=plant, **_port_kw(args),
        )
    except (PortError, HilError) as exc:
        if not interrupted():
            print(f"upright hil: {exc}", file=sys.stderr)
            return 1
        _partial(done, out, scenarios, args.tolerance)
        raise KeyboardInterrupt from None
    except KeyboardInterrupt:
        _partial(done, out, scenarios, args.tolerance)
        raise
    write_summary(runs, out, planned=scenarios, tolerance=args.tolerance)
    if json_path is not None:
        from host.hil.records import write_records

        write_records(runs, json_path)
    return report(runs, tolerance=args.tolerance, out=out)


def _port_kw(args: argparse.Namespace) -> dict[str, Any]:
    # --port: the answer times (the virtual board keeps the session's 2 s unless --timeout)
    kw: dict[str, Any] = {}
    if args.port is not None:
        kw["timeout"] = args.timeout
        kw["answer_timeout"] = args.answer_timeout
        if not args.quiet:
            kw["notice"] = lambda line: print(f"  {line}", file=sys.stderr, flush=True)
    elif args.timeout is not None:
        kw["timeout"] = args.timeout
    return kw


def _partial(done: Sequence[Any], out: Path, planned: Sequence[Any], tolerance: float) -> None:
    """After Ctrl-C: the finished runs' table and a summary file marked partial."""
    sys.stderr.write("\n")
    if done:
        report(done, tolerance=tolerance, out=out)
    path = write_summary(done, out, planned=planned, tolerance=tolerance, interrupted=True)
    print(f"interrupted: {len(done)} of {len(planned)} scenario(s) finished; partial summary: {path}", file=sys.stderr)
