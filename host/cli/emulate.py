"""``upright emulate rp2040 --pty``: an emulated Pico running the firmware, its host link on a pty.

Starts the firmware bundle on the emulated RP2040 (rp2040js, MicroPython's rp2 port: the board
as after ``make flash``), bridges its host link (UART0, 1 Mbaud) to a new pseudo-terminal, prints
the port's path on stdout (one line) and runs until Ctrl-C or end of input on stdin.  Every tool
that takes ``--port`` then works against it as against a board on ``/dev/ttyUSB0``::

    $ upright emulate rp2040 --pty
    /dev/pts/7
    $ upright proto dump --port /dev/pts/7          # in another terminal

The pendulum is held upright (ADC at the potentiometer offset) and the cart still.  The
emulation runs at about 0.1x real time: board time passes ten times slower than on the wall.
A board that does not boot or whose firmware raises ends the command with exit status 1 and
its last output.
"""

from __future__ import annotations

import argparse
import os
import select
import sys
from pathlib import Path
from typing import Any, Sequence

__all__ = ["add_arguments", "run", "hil_emulated"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright emulate``."""
    parser.add_argument("board", choices=("rp2040",), help="the emulated board (rp2040: Raspberry Pi Pico)")
    parser.add_argument("--pty", action="store_true", required=True,
                        help="bridge the board's host link (UART0) to a new pseudo-terminal and print its path")
    parser.add_argument("--bundle", metavar="DIR", default=None,
                        help="firmware bundle to put on the board's flash (default: built from firmware/)")


def _stdin_closed() -> bool:
    # end of input on stdin ends the run (a pipe closed, Ctrl-D on a terminal)
    try:
        fd = sys.stdin.fileno()
    except (AttributeError, OSError, ValueError):
        return False
    try:
        if not select.select([fd], [], [], 0)[0]:
            return False
        return os.read(fd, 4096) == b""
    except OSError:
        return True


def run(args: argparse.Namespace) -> int:
    """Run ``upright emulate``."""
    from host.boards.rp2040.board import BoardError
    from host.boards.rp2040.bridge import PtyBridge
    from host.cli.args import UsageError

    bundle = None
    if args.bundle is not None:
        bundle = Path(args.bundle)
        if not (bundle / "main.py").is_file():
            raise UsageError(f"--bundle: {bundle} holds no main.py (make firmware writes one)")
    print("upright emulate: booting the emulated RP2040 (main.py)...", file=sys.stderr, flush=True)
    try:
        bridge = PtyBridge(bundle)
    except BoardError as exc:
        return _board_failed(exc)
    try:
        print(bridge.port, flush=True)
        print(f"upright emulate: host link (UART0, {bridge.board.uart_baud} baud) on {bridge.port}; "
              "Ctrl-C or end of input stops", file=sys.stderr, flush=True)
        try:
            bridge.serve(stop=_stdin_closed)
        except BoardError as exc:
            return _board_failed(exc)
    finally:
        bridge.close()
    return 0


def _board_failed(exc: BaseException, who: str = "upright emulate") -> int:
    """One line naming the failure, then the board's last output (exit status 1)."""
    head, _, tail = str(exc).partition("\n")
    print(f"{who}: {head}", file=sys.stderr)
    if tail:
        print(tail, file=sys.stderr)
    return 1


def hil_emulated(args: argparse.Namespace, out: Path, scenarios: Sequence[Any], progress: Any,
                 json_path: Path | None, *, cli: Any) -> int:
    """``upright hil --emulate rp2040``: the scenarios on the emulated Pico, the plant on its pins.

    Same table, CSV/PNG/GIF and summary file as ``--virtual`` (:mod:`host.cli.hil`), plus the
    loop's tick time in emulated cycles; ``--json`` writes :func:`host.hil.records.scenario_record`
    per scenario.  A board that fails prints one line and its last output (exit status 1);
    Ctrl-C writes what finished, marked partial.  ``cli`` is :mod:`host.cli.hil` (its table,
    summary file and partial-run helpers; passed in, so the two modules import no circle).
    """
    from host.boards.rp2040.board import BoardError
    from host.cli.main import interrupted
    from host.hil.emulated import run_emulated
    from host.hil.errors import HilError
    from host.hil.records import write_records

    if args.link == "can":
        # the board's CAN link: its MCP2515 on SPI1 bridged to python-can (host/hil/emulated_can.py)
        from host.hil.emulated_can import run_emulated_can as run_emulated  # noqa: F811
    if not args.quiet:
        link = "CAN link: MCP2515 on SPI1, python-can virtual bus" if args.link == "can" else "UART0 link"
        print(f"upright hil: {len(scenarios)} scenario(s), emulated RP2040 (main.py, {link}, plant on the pins; "
              "about 0.1-0.2 board seconds per wall second)", file=sys.stderr)
    done: list[Any] = []
    try:
        runs = run_emulated(scenarios, out=out, compare=not args.no_compare, gif=not (args.no_gif or args.no_plots),
                            plot=not args.no_plots, progress=progress, on_result=done.append)
    except (BoardError, HilError) as exc:
        if not interrupted():
            return _board_failed(exc, "upright hil")
        cli._partial(done, out, scenarios, args.tolerance)
        raise KeyboardInterrupt from None
    except KeyboardInterrupt:
        cli._partial(done, out, scenarios, args.tolerance)
        raise
    cli.write_summary(runs, out, planned=scenarios, tolerance=args.tolerance)
    if json_path is not None:
        write_records(runs, json_path)
    status = cli.report(runs, tolerance=args.tolerance, out=out)
    for r in runs:
        st = r.stats
        print(f"  {r.name:28s} loop tick {st['tick_us_mean']:.0f} us mean, {st['tick_us_max']:.0f} us max "
              f"of {st['period_us']:.0f} us ({100 * st['tick_us_max'] / st['period_us']:.0f} %), "
              f"{st['overruns']} overrun(s); emulator {st['emu_speed']:.2f} board s per wall s", file=sys.stdout)
    return status
