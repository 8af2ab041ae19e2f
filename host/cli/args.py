"""Shared argument helpers of the ``upright`` commands: value checks, output-path checks, errors.

Every numeric flag is given one of the ``type=`` checks below, so a value that makes no sense
(``nan``, ``inf``, a negative time, a run of a billion seconds) is refused while the command
line is read, in one line naming the flag, with exit status 2 -- before any work starts.
Output paths are checked the same way (:func:`check_out_dir`, :func:`check_out_file`) before
the work, not after an hour of it.

The exit statuses, shared by every command (implemented once in :mod:`host.cli.main`):

==== ======================================================================================
0    done, every check passed
1    the run failed: its checks, a diverged simulation, a port or scheduler that cannot be
     reached, a message that does not encode or bytes that do not decode
2    refused before starting: usage, a flag value, a parameter or scenario file, an output
     path that cannot be written (:class:`UsageError`)
130  interrupted (Ctrl-C): what finished has been written, marked partial
143  the same after SIGTERM (``kill``), 129 after SIGHUP (a closed terminal): both are handled
     as Ctrl-C -- a board the tool armed is disarmed before it exits
==== ======================================================================================
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Callable

__all__ = [
    "EXIT_OK", "EXIT_FAILED", "EXIT_USAGE", "EXIT_INTERRUPTED",
    "UsageError", "RunFailed", "Terminated", "OneLineParser",
    "interrupted", "note_signal", "interrupt_signal", "reset_interrupted",
    "finite", "positive", "nonneg", "duration", "tilt", "in_range", "positive_int", "nonneg_int", "int_range",
    "nonempty", "scheduler_address", "can_interface", "check_out_dir", "check_out_file", "board_baud",
]

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

MAX_DURATION_S = 3600.0
"""Longest simulated run a command accepts (s): an hour, as the scenario files (``duration``)."""


class UsageError(ValueError):
    """Bad input found once the command line was read (a combination of flags, an output path):
    exit status 2, one line naming the flag."""


class RunFailed(RuntimeError):
    """The command ran and its result failed a check (diverged, fell, ...): exit status 1."""


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised where Ctrl-C's KeyboardInterrupt would be, so every Ctrl-C
    path (disarm the board, write what finished) runs; the exit status is 128 + signal.

    Attributes
    ----------
    signum : int
        The signal.
    """

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        super().__init__(f"signal {self.signum}")


# Ctrl-C / SIGTERM / SIGHUP seen by this process (set by host.cli.main's handlers)
_INTERRUPT = {"seen": False, "signal": 0}


def interrupted() -> bool:
    """True once SIGINT (Ctrl-C), SIGTERM or SIGHUP reached this process: a failure that
    follows it (a board that died of the same signal, a closed link) is reported as the
    interruption."""
    return bool(_INTERRUPT["seen"])


def interrupt_signal() -> int:
    """The terminating signal (SIGTERM, SIGHUP) that interrupted the run; 0 for none or Ctrl-C."""
    return int(_INTERRUPT["signal"])


def note_signal(signum: int) -> None:
    """Record that ``signum`` interrupted the run (also for code that catches the signal
    itself, such as ``upright board arm``'s hold loop): the exit status is 128 + signum
    (130 for Ctrl-C)."""
    import signal

    _INTERRUPT["seen"] = True
    if signum != signal.SIGINT and not _INTERRUPT["signal"]:
        _INTERRUPT["signal"] = int(signum)


def reset_interrupted() -> None:
    """Forget an earlier interruption (a new command starts)."""
    _INTERRUPT.update(seen=False, signal=0)


class OneLineParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line (no usage block) and exit with status 2."""

    def error(self, message: str):  # noqa: ANN201 - NoReturn
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


# ---------------------------------------------------------------- numbers
def _float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return v


def finite(text: str) -> float:
    """A finite float (no ``nan``/``inf``)."""
    return _float(text)


def positive(text: str) -> float:
    """A finite float > 0."""
    v = _float(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text!r}")
    return v


def nonneg(text: str) -> float:
    """A finite float >= 0."""
    v = _float(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text!r}")
    return v


def in_range(lo: float, hi: float, *, lo_open: bool = False, hi_open: bool = False,
             unit: str = "") -> Callable[[str], float]:
    """A finite float within ``[lo, hi]`` (``lo_open``/``hi_open``: bound excluded)."""
    u = f" {unit}" if unit else ""

    def check(text: str) -> float:
        v = _float(text)
        if (v <= lo if lo_open else v < lo) or (v >= hi if hi_open else v > hi):
            a, b = "(" if lo_open else "[", ")" if hi_open else "]"
            raise argparse.ArgumentTypeError(f"must be in {a}{lo:g}, {hi:g}{b}{u}, got {text!r}")
        return v

    check.__name__ = "number"
    return check


def duration(max_s: float = MAX_DURATION_S) -> Callable[[str], float]:
    """A simulated time in ``(0, max_s]`` seconds."""
    return in_range(0.0, max_s, lo_open=True, unit="s")


def tilt(text: str) -> float:
    """An initial tilt from upright, ``|phi| < pi/2`` rad (beyond it the pendulum lies on the cart)."""
    v = _float(text)
    if not abs(v) < math.pi / 2:
        raise argparse.ArgumentTypeError(f"must be within +-pi/2 rad (upright is 0), got {text!r}")
    return v


def _int(text: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def positive_int(text: str) -> int:
    """An integer >= 1."""
    v = _int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {v}")
    return v


def nonneg_int(text: str) -> int:
    """An integer >= 0."""
    v = _int(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {v}")
    return v


def int_range(lo: int, hi: int) -> Callable[[str], int]:
    """An integer within ``lo..hi`` (both included)."""

    def check(text: str) -> int:
        v = _int(text)
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"must be {lo}..{hi}, got {v}")
        return v

    check.__name__ = "integer"
    return check


# ---------------------------------------------------------------- strings
def nonempty(text: str) -> str:
    """A non-blank string (``--scenario ""`` is refused, not read as "nothing to do")."""
    if not text.strip() or not text.strip(", "):
        raise argparse.ArgumentTypeError(f"must not be empty, got {text!r}")
    return text


def scheduler_address(text: str) -> str:
    """A Dask scheduler address ``tcp://HOST:PORT`` (or ``tls://``, ``inproc://``, ``ucx://``)."""
    scheme, sep, rest = text.partition("://")
    if not sep or scheme not in ("tcp", "tls", "inproc", "ucx", "ws", "wss") or not rest:
        raise argparse.ArgumentTypeError(f"expected a scheduler address like tcp://HOST:8786, got {text!r}")
    return text


def can_interface(text: str) -> str:
    """A python-can interface name (``socketcan``, ``slcan``, ``pcan``, ``udp_multicast``, ...)."""
    from can.interfaces import VALID_INTERFACES

    if text not in VALID_INTERFACES:
        raise argparse.ArgumentTypeError(f"not a python-can interface: {text!r} (one of "
                                         f"{', '.join(sorted(VALID_INTERFACES))})")
    return text


def board_baud() -> int:
    """The board's UART rate (``firmware/board.py`` ``UART_BAUD``): the host tools' default."""
    from firmware.board import UART_BAUD

    return int(UART_BAUD)


# ---------------------------------------------------------------- output paths
def _can_write_in(d: Path) -> bool:
    # a real probe: os.access says yes to root even on a read-only file system
    import tempfile

    try:
        fd, name = tempfile.mkstemp(prefix=".upright-probe-", dir=d)
    except OSError:
        return False
    os.close(fd)
    os.unlink(name)
    return True


def _nearest_existing(p: Path) -> Path:
    q = p.absolute()
    while not q.exists() and q != q.parent:
        q = q.parent
    return q


def check_out_dir(path: str | Path, flag: str) -> Path:
    """Check (before any work) that directory ``path`` exists and is writable or can be created.

    Raises
    ------
    UsageError
        Naming ``flag`` and why.
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise UsageError(f"{flag} {str(path)!r}: exists and is not a directory")
    base = _nearest_existing(p)
    if not base.is_dir():
        raise UsageError(f"{flag} {str(path)!r}: {base} is not a directory")
    if not _can_write_in(base):
        raise UsageError(f"{flag} {str(path)!r}: {base} is not writable")
    return p


def check_out_file(path: str | Path | None, flag: str) -> Path | None:
    """Check (before any work) that file ``path`` can be written (``None`` and ``-`` pass).

    Raises
    ------
    UsageError
        Naming ``flag`` and why.
    """
    if path is None or str(path) == "-":
        return None
    p = Path(path)
    if not str(path).strip():
        raise UsageError(f"{flag}: empty path")
    if p.is_dir():
        raise UsageError(f"{flag} {str(path)!r}: is a directory")
    if p.exists():
        if not os.access(p, os.W_OK):
            raise UsageError(f"{flag} {str(path)!r}: not writable")
        return p
    base = _nearest_existing(p.parent)
    if not base.is_dir():
        raise UsageError(f"{flag} {str(path)!r}: {base} is not a directory")
    if not _can_write_in(base):
        raise UsageError(f"{flag} {str(path)!r}: directory {base} is not writable")
    return p
