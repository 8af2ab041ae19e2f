"""What the board says besides its loop answers: telemetry, heartbeats, acks, counted and checked.

:class:`SeqAccount` accounts for the board's periodic frames by their serial sequence number;
:class:`Sink` takes every message of a run that is not a ``hil_actuator`` answer (telemetry,
heartbeats, acks, refusals), counts it and keeps the figures a run reports
(:meth:`Sink.stats`).
"""

from __future__ import annotations

import math
import time
from typing import Any

from firmware import msgtable as T
from host.hil.errors import HilError
from host.link import messages as M

__all__ = ["TickPairs", "SeqAccount", "Sink"]

_TELEM_STATE = M.BY_NAME["telem_state"]
_TELEM_CTRL = M.BY_NAME["telem_ctrl"]
_HEARTBEAT = M.BY_NAME["heartbeat"]
_NACK = M.BY_NAME["nack"]
_ACK = M.BY_NAME["ack"]
_PARAM_VALUE = M.BY_NAME["param_value"]


class SeqAccount:
    """Accounts for the board's periodic frames by their serial sequence number: the one loss
    counter of the host (HIL runs, ``upright board log``'s recorder, the dashboard).

    Telemetry (``telem_state`` + ``telem_ctrl``, one seq for the pair) and heartbeats share
    one counter on the board, incremented once per periodic event, so the seqs seen must be
    contiguous; a gap is a lost frame, a repeat a duplicate, a step back a reordered frame
    (a late frame fills its gap again).  The 8-bit seqs are unwrapped against the newest seen
    (a step of less than 128 forward is forward); the memory is bounded: events more than
    :data:`WINDOW` behind the newest are only counted.

    Attributes
    ----------
    events : int
        Distinct periodic events seen.
    telemetry, heartbeats : int
        Distinct telemetry / heartbeat events seen.
    half_pairs : int
        Telemetry events of which only one of the two frames arrived.
    duplicates, reordered : int
        Frames seen again / seen after a later one.
    """

    #: events kept for duplicate and pair checks behind the newest (the unwrapping reaches 128)
    WINDOW = 256

    def __init__(self) -> None:
        self._last: int | None = None
        self._first: int | None = None
        self._pair: dict[int, int] = {}  # unwrapped seq -> bits seen (1 state, 2 ctrl, 4 heartbeat)
        self.events = 0
        self.telemetry = 0
        self.heartbeats = 0
        self.half_pairs = 0
        self.duplicates = 0
        self.reordered = 0

    def add(self, msg: Any, seq: int | None) -> None:
        """Feed one received message with its serial seq (others and seq None are ignored)."""
        t = type(msg)
        if seq is None or t not in (_TELEM_STATE, _TELEM_CTRL, _HEARTBEAT):
            return
        if self._last is None:
            u = seq
            self._first = u
            self._last = u
        else:
            d = (seq - self._last) & 0xFF
            u = self._last + d if d < 128 else self._last - (256 - d)
            if u > self._last:
                self._last = u
                if len(self._pair) > 2 * self.WINDOW:
                    keep = u - self.WINDOW
                    self._pair = {k: v for k, v in self._pair.items() if k >= keep}
            elif u < self._last:
                self.reordered += 1
        bit = 1 if t is _TELEM_STATE else 2 if t is _TELEM_CTRL else 4
        have = self._pair.get(u, 0)
        if have & bit:
            self.duplicates += 1
            return
        self._pair[u] = have | bit
        if have == 0:
            self.events += 1
            if bit == 4:
                self.heartbeats += 1
            else:
                self.telemetry += 1
                self.half_pairs += 1
        elif have | bit == 3:
            self.half_pairs -= 1

    @property
    def span(self) -> int:
        """Events the seqs say were sent (first to last seen)."""
        return 0 if self._first is None else self._last - self._first + 1  # type: ignore[operator]

    @property
    def lost(self) -> int:
        """Periodic events missing between the first and the last seen."""
        return self.span - self.events

    def stats(self) -> dict[str, int]:
        """All counters as a dict."""
        return {"seq_events": self.events, "seq_span": self.span, "seq_lost": self.lost,
                "telemetry": self.telemetry, "heartbeats": self.heartbeats, "duplicates": self.duplicates,
                "reordered": self.reordered, "half_pairs": self.half_pairs}


class TickPairs:
    """The two telemetry frames of one tick (``telem_state`` then ``telem_ctrl``, one seq) paired,
    every periodic frame accounted (:class:`SeqAccount`) and every broken pair counted: the one
    pairing of the board recorder (:class:`host.operate.record.Recorder`) and the dashboard
    (:class:`host.dashboard.hub.Hub`).

    Attributes
    ----------
    seqs : SeqAccount
        The sequence numbers of the periodic frames fed.
    unpaired : int
        Halves of a tick whose other half did not come (a ``telem_ctrl`` before any frame at all
        is not one: the feed started between the two halves).
    """

    def __init__(self) -> None:
        self.seqs = SeqAccount()
        self.unpaired = 0
        self._pending: tuple[Any, int | None, Any] | None = None

    @property
    def lost(self) -> int:
        """Periodic frames lost (sequence gaps) plus halves of ticks whose pair was broken."""
        return self.seqs.lost + self.unpaired

    def add(self, msg: Any, seq: int | None, t: Any = None) -> tuple[Any, Any, Any] | None:
        """Feed one message (``seq`` None: not numbered, e.g. a reply); ``(state, ctrl, t of the
        state)`` when it completes a tick's pair, else ``None``."""
        name = msg.NAME
        if name == "telem_state":
            if self._pending is not None:
                self.unpaired += 1
            self.seqs.add(msg, seq)
            self._pending = (msg, seq, t)
            return None
        if name != "telem_ctrl":
            self.seqs.add(msg, seq)
            return None
        p, self._pending = self._pending, None
        if p is None or (seq is not None and p[1] is not None and seq != p[1]):
            if self.seqs.events or p is not None:
                self.unpaired += 1
            self.seqs.add(msg, seq)
            return None
        self.seqs.add(msg, seq)
        return p[0], msg, p[2]

    def drop(self) -> None:
        """Forget a half-received tick (the end of a recording cuts it: not a loss)."""
        self._pending = None


class Sink:
    """Everything but actuator answers: telemetry (sequence-checked), heartbeats, acks.

    Parameters
    ----------
    link : Link, optional
        The link the messages come from; its ``last_seq`` (serial) is read for each message
        handed over, right after that message's ``recv``.
    strict : bool
        Raise :class:`~host.hil.errors.HilError` when the firmware refuses a loop frame
        (``hil_sensor``, ``set_reference``); ``False`` only records it (a lossy link).

    Attributes
    ----------
    acct : SeqAccount
        The periodic frames by sequence number.
    telemetry, heartbeats, acks : int
        Frames counted.
    step_us : list of int
        The firmware's step time of every ``telem_ctrl``.
    nacks : list of str
        Every refusal, with its tick.
    replies : list of (int, message)
        Every ACK, NACK and PARAM_VALUE with the tick it arrived at.
    last_state, last_faults : int
        From the last heartbeat.
    """

    def __init__(self, link: Any = None, *, strict: bool = True) -> None:
        self._link = link
        self.strict = bool(strict)
        self.acct = SeqAccount()
        self.telemetry = 0
        self.step_us: list[int] = []
        self.heartbeats = 0
        self.acks = 0
        self.nacks: list[str] = []
        self.replies: list[tuple[int, Any]] = []
        self.last_state: int | None = None
        self.last_faults = 0
        self.other_msgs = 0

    def other(self, m: Any, tick: int = -1) -> None:
        """Take one message that is not a ``hil_actuator`` answer, received at ``tick``."""
        t = type(m)
        seq = getattr(self._link, "last_seq", None) if self._link is not None else None
        self.acct.add(m, seq)
        if t is _TELEM_CTRL:
            self.telemetry += 1
            self.step_us.append(m.step_us)
        elif t is _TELEM_STATE:
            pass
        elif t is _HEARTBEAT:
            self.heartbeats += 1
            self.last_state = m.state
            self.last_faults = m.faults
        elif t is _ACK:
            self.acks += 1
            self.replies.append((tick, m))
        elif t is _NACK:
            self.nacks.append(f"tick {tick}: {m}")
            self.replies.append((tick, m))
            if self.strict and m.msg_id in (T.HIL_SENSOR, T.SET_REFERENCE):
                raise HilError(f"the firmware refused a loop frame at tick {tick}: {m}")
        elif t is _PARAM_VALUE:
            self.replies.append((tick, m))
            self.other_msgs += 1
        else:
            self.other_msgs += 1

    def drain(self, link: Any, tick: int, seconds: float = 0.05) -> None:
        """Hand what is waiting on ``link`` to :meth:`other`; bounded in time, as a board in
        real time (or one sending heartbeats) never stops talking."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            m = link.recv(0.0)
            if m is None:
                return
            self.other(m, tick)

    def stats(self) -> dict[str, Any]:
        """The figures of a run: telemetry (and what is lost of it), heartbeats, acks, step time."""
        import numpy as np  # here, not at import: the board recorder imports this module for SeqAccount

        s = np.asarray(self.step_us, dtype=float)
        return {
            "telemetry": self.telemetry,
            # periodic frames (telemetry and heartbeats share the board's counter) missing
            # by serial sequence number, half telemetry pairs included; None on CAN, whose
            # frames carry no sequence number
            "telemetry_lost": (self.acct.lost + self.acct.half_pairs) if self.acct.events else None,
            "heartbeats": self.heartbeats,
            "acks": self.acks,
            "nacks": list(self.nacks),
            "fw_step_us_mean": float(s.mean()) if s.size else math.nan,
            "fw_step_us_max": float(s.max()) if s.size else math.nan,
        }
