"""The host heartbeat, written once: one :class:`Keepalive` per link, beating in the board's time.

The host heartbeat (HOST_HEARTBEAT) is the one frame that feeds the board's link watchdog.  Every
tool that keeps a board armed sends it through the :class:`Keepalive` of its link
(:attr:`host.link.clients.Link.keepalive`): the link's own thread
(:meth:`host.link.clients.Link.start_heartbeat`), the board tools' poll loop and feeder
(:meth:`host.operate.board.Board.keepalive`) and the dashboard's pump
(:meth:`host.dashboard.hub.Hub.tick_keepalive`).

It beats every :data:`KEEPALIVE_BOARD_S` of the BOARD's clock: the link shows it every board
heartbeat (:meth:`Keepalive.observe`, ``uptime_ms`` and the wall time it arrived), a
:class:`ClockTrack` follows the board's speed from them and :func:`keepalive_period` turns it into
wall seconds -- never more often than the keepalive's full-speed period, never rarer than
:data:`KEEPALIVE_MAX_S`.  A board at full speed sees one every 50 ms of wall time; an emulated one
at 0.1x one every 250 ms of wall, 25 ms of its own: it is not flooded.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Any, Callable

from . import messages as M

__all__ = ["HOST_HEARTBEAT_S", "KEEPALIVE_BOARD_S", "KEEPALIVE_MAX_S", "MIN_SPEED", "clip_speed", "keepalive_period",
           "ClockTrack", "Keepalive"]

#: host heartbeat period (s of wall time) at full speed: well inside the smallest watchdog_ms the
#: board accepts (msgtable PARAMS) times 3
HOST_HEARTBEAT_S = 0.05

#: board seconds between two host heartbeats (the link watchdog's default is 250 ms of board time)
KEEPALIVE_BOARD_S = 0.025

#: the longest wall time between two host heartbeats, however slow the board (10 ms of board time
#: at 0.02x; a board that then jumps to 0.3x still gets one every 150 ms of its 250 ms watchdog)
KEEPALIVE_MAX_S = 0.5

#: the slowest board speed assumed (board seconds per wall second; an emulated Pico at 1/50 of real time)
MIN_SPEED = 0.02

_HOST_HEARTBEAT = M.BY_NAME["host_heartbeat"]


def clip_speed(speed: float) -> float:
    """A board speed clipped to ``[MIN_SPEED, 1]`` (a board does not run faster than real time)."""
    return max(MIN_SPEED, min(1.0, float(speed)))


def keepalive_period(speed: float, fastest: float = HOST_HEARTBEAT_S) -> float:
    """Wall seconds between two host heartbeats to a board running at ``speed``: every
    :data:`KEEPALIVE_BOARD_S` of its clock, never more often than ``fastest`` (the full-speed
    period) nor less than every :data:`KEEPALIVE_MAX_S` (or ``fastest``, if longer).

    A host heartbeat every 50 ms of WALL time is one every 1-4 ticks of a board at 0.02-0.15x:
    balancing with telemetry every tick its link budget takes about one frame in 8 ticks, the
    rest waits (``link_wait_max`` 202 ticks seen), the receive buffer overflows and no heartbeat
    arrives whole -- the board's watchdog latches while the host sends.  In board time the
    cadence is the one a real board sees."""
    return min(max(KEEPALIVE_MAX_S, float(fastest)), max(float(fastest), KEEPALIVE_BOARD_S / clip_speed(speed)))


class ClockTrack:
    """The board's speed followed from its heartbeats (``uptime_ms``, low 16 bits, and the wall
    time each arrived): the board's seconds per wall second over the last ``window`` s.

    The estimate errs fast: heartbeats that arrive bunched (a host that read late) read as a
    fast board, hence more host heartbeats, not fewer."""

    def __init__(self, window: float = 1.0, speed: float = 1.0) -> None:
        self.window = float(window)
        self.speed = clip_speed(speed)
        self._seen: collections.deque[tuple[int, float]] = collections.deque(maxlen=64)

    def observe(self, uptime_ms: int, t: float) -> float:
        """One heartbeat; returns the speed now."""
        seen = self._seen
        if seen and ((int(uptime_ms) - seen[-1][0]) % 65536) >= 32768:
            seen.clear()  # went backwards: a reset (or a reply out of order): start again
        seen.append((int(uptime_ms) & 0xFFFF, float(t)))
        while len(seen) > 2 and t - seen[1][1] >= self.window:
            seen.popleft()
        u0, t0 = seen[0]
        if t - t0 >= 0.5 * self.window:
            board_s = ((int(uptime_ms) - u0) % 65536) / 1000.0
            self.speed = clip_speed(board_s / (t - t0))
        return self.speed


class Keepalive:
    """The host heartbeat of one link, due every :data:`KEEPALIVE_BOARD_S` of the board's clock.

    Parameters
    ----------
    send : callable
        Sends one message (a link's ``send``: thread-safe, several threads may tick).
    period : float
        Wall seconds between heartbeats to a board at full speed (the fastest cadence); a slower
        board gets them every :data:`KEEPALIVE_BOARD_S` of its own clock (:attr:`period`).
    """

    def __init__(self, send: Callable[[M.Message], Any], period: float = HOST_HEARTBEAT_S) -> None:
        if period <= 0:
            raise ValueError(f"period must be > 0, got {period!r}")
        self._send = send
        self.fastest = float(period)
        #: the board's speed, followed from its heartbeats (:meth:`observe`)
        self.clock = ClockTrack()
        self.last = -float("inf")
        #: host heartbeats sent
        self.sent = 0
        self._lock = threading.Lock()

    @property
    def period(self) -> float:
        """Wall seconds between two heartbeats now (:func:`keepalive_period` of the board's speed)."""
        return keepalive_period(self.clock.speed, self.fastest)

    def observe(self, uptime_ms: int, t: float | None = None) -> None:
        """A board heartbeat (its ``uptime_ms``) arrived at wall time ``t``: follow the board's clock."""
        self.clock.observe(uptime_ms, time.monotonic() if t is None else t)

    def restart(self, speed: float) -> None:
        """Follow the board's clock afresh from a measured ``speed`` (board s per wall s)."""
        self.clock = ClockTrack(speed=speed)

    def beat(self, now: float | None = None) -> None:
        """Send one host heartbeat now (the next is due a period later even if this one failed)."""
        self.fed(now)
        self._send(_HOST_HEARTBEAT())
        self.sent += 1

    def fed(self, now: float | None = None) -> None:
        """The watchdog was fed at ``now`` (a heartbeat, or another frame that feeds it)."""
        self.last = time.monotonic() if now is None else now

    def due_in(self, now: float | None = None) -> float:
        """Wall seconds until the next heartbeat is due (<= 0: due now)."""
        now = time.monotonic() if now is None else now
        return self.last + self.period - now

    def tick(self, now: float | None = None) -> bool:
        """Send a host heartbeat if a :attr:`period` passed since the last feed; True if sent."""
        now = time.monotonic() if now is None else now
        with self._lock:  # two threads ticking the one keepalive send one heartbeat, not two
            if now - self.last < self.period:
                return False
            self.beat(now)
        return True
