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
:func:`wall_time` for any wait stated in board seconds.
"""

from __future__ import annotations

import collections
import time
from firmware import msgtable as T
from host.hil.errors import HilError
from host.link import messages as M
from host.link.clients import Link, LinkTimeout

__all__ = ["BASE_S", "MAX_S", "REQUEST_S", "REQUEST_MAX_S", "first_answer", "board_speed", "answer_time",
           "request_time", "wall_time", "keepalive_period", "ClockTrack", "KEEPALIVE_BOARD_S", "KEEPALIVE_MAX_S",
           "describe"]

#: seconds of wall time per answer for a board at full speed
BASE_S = 2.0
#: the longest automatic answer time (a board at 1/50 of real time)
MAX_S = 100.0
_MIN_SPEED = BASE_S / MAX_S
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


def _clip(speed: float) -> float:
    return max(_MIN_SPEED, min(1.0, float(speed)))


def request_time(speed: float, base: float = REQUEST_S) -> float:
    """Seconds of wall time per request attempt to a board running at ``speed`` (``base`` at full
    speed, at most :data:`REQUEST_MAX_S`)."""
    return min(max(REQUEST_MAX_S, base), base / _clip(speed))


def wall_time(board_s: float, speed: float) -> float:
    """Wall seconds in which a board running at ``speed`` lives ``board_s`` seconds of its own clock."""
    return float(board_s) / _clip(speed)


#: board seconds between two host heartbeats (the link watchdog's default is 250 ms of board time)
KEEPALIVE_BOARD_S = 0.025


#: the longest wall time between two host heartbeats, however slow the board (10 ms of board time
#: at 0.02x; a board that then jumps to 0.3x still gets one every 150 ms of its 250 ms watchdog)
KEEPALIVE_MAX_S = 0.5


def keepalive_period(speed: float, fastest: float = 0.05) -> float:
    """Wall seconds between two host heartbeats to a board running at ``speed``: every
    :data:`KEEPALIVE_BOARD_S` of its clock, never more often than ``fastest`` (the full-speed
    period, ``host.link.clients.HOST_HEARTBEAT_S``) nor less than every :data:`KEEPALIVE_MAX_S`.

    A host heartbeat every 50 ms of WALL time is one every 1-4 ticks of a board at 0.02-0.15x:
    balancing with telemetry every tick its link budget takes about one frame in 8 ticks, the
    rest waits (``link_wait_max`` 202 ticks seen), the receive buffer overflows and no heartbeat
    arrives whole -- the board's watchdog latches while the host sends.  In board time the
    cadence is the one a real board sees."""
    return min(KEEPALIVE_MAX_S, max(float(fastest), KEEPALIVE_BOARD_S / _clip(speed)))


class ClockTrack:
    """The board's speed followed from its periodic heartbeats (``uptime_ms``, low 16 bits, and
    the wall time each arrived): the board's seconds per wall second over the last ``window`` s.

    The estimate errs fast: heartbeats that arrive bunched (a host that read late) read as a
    fast board, hence more host heartbeats, not fewer."""

    def __init__(self, window: float = 1.0, speed: float = 1.0) -> None:
        self.window = float(window)
        self.speed = _clip(speed)
        self._seen: collections.deque[tuple[int, float]] = collections.deque(maxlen=64)

    def observe(self, uptime_ms: int, t: float) -> float:
        """One periodic heartbeat; returns the speed now."""
        seen = self._seen
        if seen and ((int(uptime_ms) - seen[-1][0]) % 65536) >= 32768:
            seen.clear()  # went backwards: a reset (or a reply out of order): start again
        seen.append((int(uptime_ms) & 0xFFFF, float(t)))
        while len(seen) > 2 and t - seen[1][1] >= self.window:
            seen.popleft()
        u0, t0 = seen[0]
        if t - t0 >= 0.5 * self.window:
            board_s = ((int(uptime_ms) - u0) % 65536) / 1000.0
            self.speed = _clip(board_s / (t - t0))
        return self.speed


def describe(speed: float, timeout: float) -> str:
    """One line for the run's header."""
    return f"board clock at {speed:.2f}x the wall's: {timeout:.0f} s per answer (--timeout fixes it)"
