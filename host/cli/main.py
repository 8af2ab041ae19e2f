"""The ``upright`` command line.

Each subcommand lives in its own module that provides ``add_arguments(parser)`` and
``run(args) -> int``; the table below maps command names to those modules, which are
imported only when their command runs (nothing is parsed or imported at import time).
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
from typing import Sequence

from host.cli import args as A
from host.cli.args import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_USAGE, OneLineParser, RunFailed, Terminated, UsageError

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("host.cli.simulate", "integrate the nonlinear plant, open loop or closed around a design; write CSV"),
    "design": ("host.cli.design", "print the design report (poles, gains, margins, constraint checks) and write figures"),
    "report": ("host.cli.report", "reproduce the numbers the design report publishes (report seed [--json])"),
    "export": ("host.cli.export", "write the fixed-point gain table module for the firmware"),
    "generate": ("host.cli.generate", "regenerate every generated file (or --check that none is stale)"),
    "proto": ("host.cli.proto", "encode/decode protocol messages (serial or CAN framing) and dump a live link"),
    "hil": ("host.cli.hil", "close the firmware in a hardware-in-the-loop run with the simulated plant"),
    "emulate": ("host.cli.emulate", "the virtual robot: the firmware on an emulated board (rp2040), the simulated "
                                     "robot on its pins, its host link on a pty (--pty) or CAN bus (--can); "
                                     "Ctrl-C or SIGTERM stops it"),
    "board": ("host.cli.board", "operate a board: status, arm/disarm, parameters, gains, log, calibrate, excite"),
    "identify": ("host.cli.identify", "estimate the robot's parameters (inertia, mL, friction, motor, delay, pot "
                                      "offset) from excite logs; write a robot TOML"),
    "commission": ("host.cli.commission", "first power-up to a verified robot: checks, calibration, cart-only and "
                                          "balancing runs, identification, design with margin, verification, report"),
    "sweep": ("host.cli.sweep", "batch Monte Carlo: robustness, weight tuning, largest recoverable tilt"),
    "soak": ("host.cli.soak", "long lockstep HIL run: firmware heap, timing drift, telemetry accounted for, metrics stable"),
    "dashboard": ("host.cli.dashboard", "a live web page for a board: plots, state, arm/disarm, reference, gains, recording"),
    "demo": ("host.cli.demo", "the main job: the report's scenarios balanced by the firmware, summary and plots"),
}


def _lazy_module(name: str):  # noqa: ANN202 - returns a module
    return importlib.import_module(COMMANDS[name][0])


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """Build the top-level parser with one subparser per command.

    Parameters
    ----------
    only : str, optional
        Import and define the arguments of this command only (the others keep their
        one-line help), so ``upright simulate ...`` does not import the HIL, the sweeps...

    Returns
    -------
    argparse.ArgumentParser
    """
    parser = OneLineParser(
        prog="upright",
        description="Design, simulate and run the firmware of a motorised inverted pendulum on a cart.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_) in COMMANDS.items():
        sp = sub.add_parser(name, help=help_, description=help_)
        sp.set_defaults(_command=name)
        # argument definitions are imported with the command's module
        if only is not None and name != only:
            continue
        try:
            _lazy_module(name).add_arguments(sp)
        except ModuleNotFoundError as exc:  # pragma: no cover - a command not built yet
            if exc.name != COMMANDS[name][0]:
                raise
            sp.set_defaults(_missing=True)
    return parser


#: signals handled as Ctrl-C (the board disarmed, what finished written), exit 128 + signal
TERMINATING = (signal.SIGTERM, signal.SIGHUP)
#: commands that handle SIGTERM/SIGHUP themselves
_OWN_SIGNALS = ("emulate",)

# the flags live in host.cli.args: ``python -m host.cli.main`` runs this file as __main__,
# and a command module importing host.cli.main would get a second copy of module globals
interrupted = A.interrupted
note_signal = A.note_signal


def _on_sigint(signum: int, frame: object) -> None:
    note_signal(signum)
    raise KeyboardInterrupt


def _on_terminate(signum: int, frame: object) -> None:
    # the first SIGTERM/SIGHUP interrupts like Ctrl-C; one that comes while the tool winds
    # down (a closed terminal sends SIGHUP, then the shell may send SIGTERM) must not cut
    # the disarm short
    first = not A.interrupt_signal()
    note_signal(signum)
    if first:
        raise Terminated(signum)


def _install_sigint(command: str | None = None) -> dict[int, object]:
    A.reset_interrupted()
    old: dict[int, object] = {}
    try:
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            old[signal.SIGINT] = signal.signal(signal.SIGINT, _on_sigint)
        if command not in _OWN_SIGNALS:
            for s in TERMINATING:
                # a signal ignored by the caller (nohup) stays ignored
                if signal.getsignal(s) is signal.SIG_DFL:
                    old[s] = signal.signal(s, _on_terminate)
    except ValueError:  # pragma: no cover - not the main thread
        pass
    return old


def _restore_sigint(old: dict[int, object]) -> None:
    for s, h in old.items():
        try:
            signal.signal(s, h)  # type: ignore[arg-type]
        except ValueError:  # pragma: no cover
            pass


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``upright`` console script.

    Exit status (every command): 0 done; 1 the run failed (its checks, a diverged run, a
    port or scheduler that cannot be reached); 2 bad input or usage, refused before the work
    starts; 130 interrupted (Ctrl-C), after writing what finished; 143 / 129 the same after
    SIGTERM / SIGHUP (a closed terminal): handled as Ctrl-C -- a board this tool armed is
    disarmed first.

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments (default: ``sys.argv[1:]``).

    Returns
    -------
    int
        Process exit status.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    chosen = next((a for a in argv if not a.startswith("-")), None)
    old = _install_sigint(chosen)
    name = "upright"
    try:
        parser = build_parser(only=chosen if chosen in COMMANDS else "")
        args = parser.parse_args(argv)
        if getattr(args, "_command", None) is None:
            parser.print_help()
            return EXIT_USAGE
        name = f"upright {args._command}"
        return _run(name, args)
    except KeyboardInterrupt:
        return _interrupted(name)
    finally:
        _restore_sigint(old)


def _interrupted(name: str) -> int:
    sig = A.interrupt_signal()
    if sig:
        _tell(f"\n{name}: interrupted by {signal.Signals(sig).name}")
        _quiet_lost_streams()
        return 128 + sig
    _tell(f"\n{name}: interrupted")
    return EXIT_INTERRUPTED


def _tell(text: str) -> None:
    # stderr may be gone (a closed terminal): the exit status still says what happened
    try:
        print(text, file=sys.stderr, flush=True)
    except (OSError, ValueError):
        pass


def _quiet_lost_streams() -> None:
    # a closed terminal: flushing stdout at exit would fail and turn the status into 120
    for fd, stream in ((1, sys.stdout), (2, sys.stderr)):
        try:
            stream.flush()
        except (OSError, ValueError):
            try:
                null = os.open(os.devnull, os.O_WRONLY)
                os.dup2(null, fd)
                os.close(null)
            except OSError:
                pass


def _run(name: str, args: argparse.Namespace) -> int:
    from sim.params import ParamError
    from sim.scenario import ScenarioError

    try:
        return int(_lazy_module(args._command).run(args) or 0)
    except KeyboardInterrupt:
        raise
    except ParamError as exc:
        status, text = EXIT_USAGE, f"bad parameter: {exc}"
    except ScenarioError as exc:
        status, text = EXIT_USAGE, f"bad scenario: {exc}"
    except UsageError as exc:
        status, text = EXIT_USAGE, f"error: {exc}"
    except RunFailed as exc:
        status, text = EXIT_FAILED, f"failed: {exc}"
    except (OSError, ValueError) as exc:
        status, text = EXIT_FAILED, f"error: {exc}"
    except RuntimeError as exc:  # the project's own run errors (HilError, DaskRunError, ...)
        if type(exc).__module__.split(".")[0] not in ("host", "sim"):
            raise
        status, text = EXIT_FAILED, f"error: {exc}"
    if interrupted():
        return _interrupted(name)
    _tell(f"{name}: {' '.join(text.split())}")
    return status


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
