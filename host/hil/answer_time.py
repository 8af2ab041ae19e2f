"""How long a HIL host waits for a board's answers: the first one, and each one after it.

A board at full speed answers a request within milliseconds, so two seconds of wall time per
answer is plenty; an emulated Pico (the virtual robot, ``upright emulate rp2040 --pty``) runs
at 0.05-0.4x real time on a loaded machine, and the same answer then takes 3-20 times longer on
the wall.  :func:`board_speed` measures the board's clock against the host's (two heartbeats'
``uptime_ms`` one wall second apart) and :func:`answer_time` scales the wait by it, so
``upright hil --port`` works unchanged against either (``--timeout`` fixes it instead).

The board tools (:class:`host.operate.board.Board`: ``upright board status``, ``log``, ``excite``,
``calibrate``, ``gains upload``, ``upright commission --port``) use the same measurement for
their own waits: :func:`request_time` per request attempt (:data:`REQUEST_S` at full speed) and
:func:`wall_time` for any wait stated in board seconds.  The host heartbeat's cadence in board
time (:func:`keepalive_period`, :class:`ClockTrack`) is the link's (:mod:`host.link.keepalive`),
named here too.
"""

from __future__ import annotations

import collections
import time
from firmware import msgtable as T
from host.hil.errors import HilError
from host.link import messages as M
from host.link.clients import Link, LinkTimeout
from host.link.keepalive import KEEPALIVE_BOARD_S, KEEPALIVE_MAX_S, MIN_SPEED, ClockTrack, keepalive_period
from host.link.keepalive import clip_speed as _clip

__all__ = ["BASE_S", "MAX_S", "REQUEST_S", "REQUEST_MAX_S", "first_answer", "board_speed", "answer_time",
           "request_time", "wall_time", "keepalive_period", "ClockTrack", "KEEPALIVE_BOARD_S", "KEEPALIVE_MAX_S",
           "describe"]

#: seconds of wall time per answer for a board at full speed
BASE_S = 2.0
#: the longest automatic answer time (a board at 1/50 of real time)
MAX_S = 100.0
_MIN_SPEED = MIN_SPEED  # BASE_S / MAX_S: the slowest board the keepalive assumes
#: seconds of wall time per request attempt of the board tools, for a board at full speed
REQUEST_S = 0.3
#: the longest automatic request attempt (a board at 1/33 of real time and slower)
REQUEST_MAX_S = 10.0
_REQUEST = M.BY_NAME["request"]


def _heartbeat(link: Link, timeout: float) -> tuple[int, float]:
    m = link.request(_REQUEST(msg_id=T.HEARTBEAT), timeout=timeout, retries=0)
    return int(getattr(m, "uptime_ms")), time.monotonic()


def first_answer(link: Link, port: str, within: float) -> tuple[int, float]:
    """Ask for a heartbeat until the board answers; return its ``uptime_ms`` and the wall time.

    Raises
    ------
    HilError
        No answer within ``within`` s (one line naming the port and ``--answer-timeout``).
    """
    deadline = time.monotonic() + within
    while True:
        left = deadline - time.monotonic()
        try:
            return _heartbeat(link, max(0.05, min(1.0, left)))
        except LinkTimeout:
            if time.monotonic() >= deadline:
                raise HilError(f"no answer from {port} within {within:g} s (--answer-timeout): is the board "
                               "powered, running the upright firmware, on this port and baud rate?") from None


def board_speed(link: Link, first: tuple[int, float], wall_s: float = 1.0, timeout: float = MAX_S) -> float:
    """Board seconds per wall second, from ``first`` (see :func:`first_answer`) and a heartbeat
    ``wall_s`` later; clipped to ``[BASE_S / MAX_S, 1]`` (a board does not run faster than
    real time; one in HIL mode whose clock stands still gets the longest wait).

    Raises
    ------
    HilError
        The second heartbeat did not come within ``timeout`` s.
    """
    u0, t0 = first
    time.sleep(max(0.0, t0 + wall_s - time.monotonic()))
    try:
        u1, t1 = _retry(link, timeout)
    except LinkTimeout:
        raise HilError(f"the board stopped answering (no heartbeat within {timeout:g} s)") from None
    board_s = ((u1 - u0) % 65536) / 1000.0  # HEARTBEAT.uptime_ms: the low 16 bits
    return min(1.0, max(_MIN_SPEED, board_s / max(1e-3, t1 - t0)))


def _retry(link: Link, timeout: float) -> tuple[int, float]:
    deadline = time.monotonic() + timeout
    while True:
        try:
            return _heartbeat(link, max(0.05, min(1.0, deadline - time.monotonic())))
        except LinkTimeout:
            if time.monotonic() >= deadline:
                raise


def answer_time(speed: float) -> float:
    """Seconds of wall time to wait for one answer of a board running at ``speed``."""
    return min(MAX_S, BASE_S / max(_MIN_SPEED, min(1.0, float(speed))))


def request_time(speed: float, base: float = REQUEST_S) -> float:
    """Seconds of wall time per request attempt to a board running at ``speed`` (``base`` at full
    speed, at most :data:`REQUEST_MAX_S`)."""
    return min(max(REQUEST_MAX_S, base), base / _clip(speed))


def wall_time(board_s: float, speed: float) -> float:
    """Wall seconds in which a board running at ``speed`` lives ``board_s`` seconds of its own clock."""
    return float(board_s) / _clip(speed)


def describe(speed: float, timeout: float) -> str:
    """One line for the run's header."""
    return f"board clock at {speed:.2f}x the wall's: {timeout:.0f} s per answer (--timeout fixes it)"
