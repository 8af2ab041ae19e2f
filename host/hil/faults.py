"""Fault injection for the HIL loop: the link, the sensors and the actuator, seeded and counted.

Everything here sits on the *host* side of the loop, so the firmware and the protocol code
run unchanged while the world around them misbehaves:

link (byte stream / frames)
    :class:`FrameFaults` decides, frame by frame, with a seeded RNG, whether a frame is
    passed, dropped, bit-flipped, shortened by one byte, duplicated or held back and sent
    after the next one (reordered), and counts what it did.  :class:`StreamFaults` applies
    it to a byte stream (the ``fault_tx``/``fault_rx`` hooks of :class:`host.hil.session.HilSession`,
    i.e. :class:`host.hil.session.FaultyPort`): serial COBS frames are split on their ``0x00``
    delimiters; on the CAN link every write is one python-can ``serial`` frame.  Setting
    ``cut = True`` swallows everything (link loss) until it is set back.
    :class:`BusFaults` does the same for received CAN frames at the python-can ``recv``
    level.  Bit flips and shortened frames are refused on CAN: a real CAN controller
    checks its CRC-15 and never delivers such a frame -- there it is a drop.
sensors
    :class:`SensorFault` transforms the ``(adc, enc)`` reading the plant produced before it
    is sent: ADC at a rail, ADC floating (uniform noise over the whole range), encoder
    stuck, encoder jumping, readings delayed by extra ticks.
actuator
    :class:`ActuatorFault`: from a given tick the plant ignores the motor command (a dead
    driver or an open motor lead).
loop
    :func:`run_lossy` is a lockstep loop that survives a lossy link the way a real loop
    does: the plant advances every tick; if the board's answer for the tick does not come
    within ``answer_timeout`` the previous duty is held (the PWM keeps its last value) and
    the tick is counted lost; stale answers are discarded.  It accounts for every periodic
    frame (telemetry, heartbeat) by its sequence number (:class:`SeqAccount`).
firmware probe
    :class:`ProbeSession` is a :class:`host.hil.session.HilSession` whose virtual board runs the
    unchanged HIL main inside a small wrapper that holds ``micropython.heap_lock()`` for the
    whole run (lockstep) and prints, at exit, the heap in use before and after and the
    firmware decoder's own drop counters -- the board exposes neither over the link.
"""

from __future__ import annotations

import math
import random
import re
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from host.link import messages as M
from host.hil.session import HilError, HilSession
from host.link.clients import CanLink, LinkError, SerialLink
from sim.params import RobotParams, load_params
from sim.plantsim import PlantSim
from sim.scenario import Scenario

__all__ = [
    "FaultError",
    "FrameFaults",
    "StreamFaults",
    "BusFaults",
    "Tap",
    "SensorFault",
    "ActuatorFault",
    "SeqAccount",
    "LossyRun",
    "run_lossy",
    "stream_realtime",
    "ProbeSession",
    "FdPort",
    "serial_link_on_fd",
    "SENSOR_KINDS",
]

SENSOR_KINDS = ("adc_low", "adc_high", "adc_float", "enc_stuck", "enc_jump", "delay")
"""Sensor faults :class:`SensorFault` can inject."""

_ACTUATOR = M.BY_NAME["hil_actuator"]
_SENSOR = M.BY_NAME["hil_sensor"]
_SET_REF = M.BY_NAME["set_reference"]
_TELEM_STATE = M.BY_NAME["telem_state"]
_TELEM_CTRL = M.BY_NAME["telem_ctrl"]
_HEARTBEAT = M.BY_NAME["heartbeat"]


class FaultError(ValueError):
    """A fault injector was configured with values it cannot honour."""


def _rate(name: str, v: float) -> float:
    v = float(v)
    if not 0.0 <= v <= 1.0 or math.isnan(v):
        raise FaultError(f"{name} must be a probability in [0, 1], got {v!r}")
    return v


# ---------------------------------------------------------------- link faults
class FrameFaults:
    """Per-frame link faults with a seeded RNG and counters.

    Parameters
    ----------
    seed : int
        RNG seed (the same seed gives the same faults for the same frames).
    flip : float
        Probability that a frame gets one random bit flipped (never in a delimiter).
    drop : float
        Probability that a frame is dropped whole.
    drop_byte : float
        Probability that one random byte of a frame is dropped.
    dup : float
        Probability that a frame is sent twice.
    reorder : float
        Probability that a frame is held back and sent after the next one.
    can : bool
        The frames are CAN frames: ``flip`` and ``drop_byte`` must be 0 (the controller's
        CRC turns them into drops).

    Attributes
    ----------
    counts : dict
        ``frames`` seen, ``passed`` unchanged (duplicates included), ``dropped``,
        ``flipped``, ``byte_dropped``, ``duplicated``, ``reordered``, ``cut`` (frames
        swallowed while cut).
    cut : bool
        While True every frame is swallowed (link loss).
    enabled : bool
        While False every frame passes (counted); set it to start the faults after a
        clean set-up.
    """

    def __init__(self, *, seed: int = 0, flip: float = 0.0, drop: float = 0.0, drop_byte: float = 0.0,
                 dup: float = 0.0, reorder: float = 0.0, can: bool = False) -> None:
        self.flip = _rate("flip", flip)
        self.drop = _rate("drop", drop)
        self.drop_byte = _rate("drop_byte", drop_byte)
        self.dup = _rate("dup", dup)
        self.reorder = _rate("reorder", reorder)
        if self.flip + self.drop + self.drop_byte + self.dup + self.reorder > 1.0:
            raise FaultError("the fault probabilities must add up to at most 1")
        if can and (self.flip or self.drop_byte):
            raise FaultError("bit flips and shortened frames cannot reach a CAN node (the controller's CRC "
                             "drops them): use drop")
        self.can = bool(can)
        self.seed = int(seed)
        self._rng = random.Random(self.seed)
        self._held: bytes | None = None
        self.cut = False
        self.enabled = True
        self.counts = {k: 0 for k in ("frames", "passed", "dropped", "flipped", "byte_dropped",
                                      "duplicated", "reordered", "cut")}

    @property
    def rate(self) -> float:
        """Total probability that a frame is disturbed."""
        return self.flip + self.drop + self.drop_byte + self.dup + self.reorder

    @property
    def corrupted(self) -> int:
        """Frames delivered with wrong content (bit flipped or byte dropped)."""
        return self.counts["flipped"] + self.counts["byte_dropped"]

    def apply(self, frame: bytes) -> list[bytes]:
        """The frames to deliver in place of ``frame`` (0, 1 or 2 of them, maybe a held one)."""
        c = self.counts
        c["frames"] += 1
        if self.cut:
            c["cut"] += 1
            return []
        if not self.enabled:
            c["passed"] += 1
            return [frame]
        r = self._rng.random()
        out: list[bytes] = []
        lim = self.drop
        if r < lim:
            c["dropped"] += 1
        elif r < (lim := lim + self.flip):
            b = bytearray(frame)
            i = self._rng.randrange(len(b))
            b[i] ^= 1 << self._rng.randrange(8)
            c["flipped"] += 1
            out.append(bytes(b))
        elif r < (lim := lim + self.drop_byte) and len(frame) > 1:
            i = self._rng.randrange(len(frame))
            c["byte_dropped"] += 1
            out.append(frame[:i] + frame[i + 1:])
        elif r < (lim := lim + self.dup):
            c["duplicated"] += 1
            c["passed"] += 2
            out += [frame, frame]
        elif r < lim + self.reorder and self._held is None:
            c["reordered"] += 1
            self._held = frame
            return []
        else:
            c["passed"] += 1
            out.append(frame)
        if self._held is not None:
            c["passed"] += 1
            out.append(self._held)
            self._held = None
        return out

    def flush(self) -> list[bytes]:
        """A frame still held back for reordering (delivered now)."""
        if self._held is None:
            return []
        h, self._held = self._held, None
        self.counts["passed"] += 1
        return [h]


class StreamFaults:
    """A byte-stream hook (``bytes -> bytes``) that applies :class:`FrameFaults` per frame.

    Parameters
    ----------
    link : {"serial", "can"}
        ``"serial"``: COBS frames delimited by ``0x00`` (bytes of an unfinished frame are
        kept until its delimiter arrives, so a read may return fewer bytes).  ``"can"``:
        each call is one python-can ``serial`` frame (python-can writes one per call; use
        only as a *write* hook -- its reader needs exact byte counts, see
        :class:`BusFaults` for the receive side).
    **rates
        Passed to :class:`FrameFaults` (``seed``, ``flip``, ``drop``, ...).

    Examples
    --------
    >>> tx = StreamFaults("serial", seed=1, flip=0.05)          # doctest: +SKIP
    >>> HilSession(fault_tx=tx)                                 # doctest: +SKIP
    """

    def __init__(self, link: str = "serial", **rates: Any) -> None:
        if link not in ("serial", "can"):
            raise FaultError(f"link must be 'serial' or 'can', got {link!r}")
        self.link = link
        self.faults = FrameFaults(can=link == "can", **rates)
        self._part = bytearray()

    @property
    def counts(self) -> dict[str, int]:
        """The counters of :class:`FrameFaults`."""
        return self.faults.counts

    @property
    def cut(self) -> bool:
        """Link loss: while True nothing passes."""
        return self.faults.cut

    @cut.setter
    def cut(self, v: bool) -> None:
        self.faults.cut = bool(v)
        if v:
            self._part.clear()

    def __call__(self, data: bytes) -> bytes:
        f = self.faults
        if self.link == "can":
            return b"".join(f.apply(bytes(data)))
        out = bytearray()
        start = 0
        while True:
            j = data.find(b"\x00", start)
            if j < 0:
                self._part += data[start:]
                break
            body = bytes(self._part) + data[start:j]
            self._part.clear()
            start = j + 1
            if not body:
                continue
            for fr in f.apply(body):
                out += b"\x00" + fr + b"\x00"
        return bytes(out)


class BusFaults:
    """A python-can bus proxy whose ``recv`` drops, duplicates or reorders frames.

    Install it as the ``bus`` of a :class:`host.link.clients.CanLink` (``link.bus = BusFaults(link.bus,
    ...)``); everything but ``recv`` goes to the real bus.

    Parameters
    ----------
    bus : can.BusABC
        The real bus.
    **rates
        ``seed``, ``drop``, ``dup``, ``reorder`` (see :class:`FrameFaults`).
    """

    def __init__(self, bus: Any, **rates: Any) -> None:
        object.__setattr__(self, "_bus", bus)
        object.__setattr__(self, "faults", FrameFaults(can=True, **rates))
        object.__setattr__(self, "_ready", [])

    @property
    def counts(self) -> dict[str, int]:
        """The counters of :class:`FrameFaults`."""
        return self.faults.counts

    def recv(self, timeout: float | None = None) -> Any:
        if self._ready:
            return self._ready.pop(0)
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            frame = self._bus.recv(left)
            if frame is None:
                return None
            # the frame object itself stands in for its bytes
            out = self.faults.apply(frame)  # type: ignore[arg-type]
            if out:
                self._ready.extend(out[1:])
                return out[0]

    def __getattr__(self, name: str) -> Any:
        return getattr(self._bus, name)


class Tap:
    """A byte-stream hook that passes data on and decodes a copy (what the host received).

    Use it as a ``fault_rx`` hook (alone, or chained after a fault hook with ``inner``) to
    see every frame the board sent, with the host's receive time, even while the runner's
    own loop consumes them.

    Parameters
    ----------
    link : {"serial", "can"}
        Framing of the stream (CAN: python-can ``serial``-interface frames).
    inner : callable, optional
        A hook applied first (e.g. :class:`StreamFaults`); the tap sees its output.
    cut : bool
        Start with the stream cut (nothing passes) -- see :attr:`cut`.

    Attributes
    ----------
    messages : list of (float, Message, int or None)
        ``(time.monotonic(), message, seq)`` of every decoded frame.
    cut : bool
        While True nothing passes (and nothing is recorded): link loss on this direction.
    """

    def __init__(self, link: str = "serial", inner: Callable[[bytes], bytes] | None = None,
                 cut: bool = False) -> None:
        if link not in ("serial", "can"):
            raise FaultError(f"link must be 'serial' or 'can', got {link!r}")
        self.link = link
        self.inner = inner
        self.cut = bool(cut)
        self.messages: list[tuple[float, Any, int | None]] = []
        self._dec = M.SerialStreamDecoder()
        self._buf = bytearray()

    def __call__(self, data: bytes) -> bytes:
        if self.cut:
            return b""
        if self.inner is not None:
            data = self.inner(data)
        now = time.monotonic()
        if self.link == "serial":
            for m, seq in self._dec.feed(data):
                self.messages.append((now, m, seq))
        else:
            b = self._buf
            b += data
            while True:
                i = b.find(0xAA)
                if i < 0:
                    b.clear()
                    break
                del b[:i]
                if len(b) < 6:
                    break
                dlc = b[5]
                if dlc > 8:
                    del b[:1]
                    continue
                need = 11 + dlc
                if len(b) < need:
                    break
                if b[need - 1] == 0xBB:
                    cid = int.from_bytes(b[6:10], "little")
                    try:
                        _, m = M.decode_can(cid & 0x7FF, bytes(b[10:10 + dlc]))
                        self.messages.append((now, m, None))
                    except M.FrameError:
                        pass
                    del b[:need]
                else:
                    del b[:1]
        return data

    def of(self, name: str) -> list[tuple[float, Any, int | None]]:
        """The recorded frames of one message name (``"heartbeat"``, ...)."""
        return [r for r in self.messages if r[1].NAME == name]


# ---------------------------------------------------------------- sensor / actuator faults
class SensorFault:
    """A sensor fault applied to the readings the plant produced, from tick ``start``.

    Parameters
    ----------
    kind : str
        One of :data:`SENSOR_KINDS`: ``adc_low`` / ``adc_high`` (potentiometer open or
        shorted: the ADC at 0 or full scale), ``adc_float`` (wiper disconnected: uniform
        noise over the whole ADC range), ``enc_stuck`` (the counter freezes), ``enc_jump``
        (the counter jumps by ``jump`` counts once, then keeps the offset), ``delay``
        (readings ``delay`` ticks older than they should be).
    start : int
        First tick affected.
    stop : int, optional
        First tick no longer affected (default: never); an encoder jump keeps its offset.
    params : RobotParams, optional
        For the ADC range (``adc_bits``); default ``sim/robot.toml``.
    seed : int
        RNG seed for ``adc_float``.
    jump : int
        Encoder jump (counts).
    delay : int
        Extra delay (ticks) for ``delay``.

    Attributes
    ----------
    applied : int
        Readings changed so far.
    """

    def __init__(self, kind: str, start: int, *, stop: int | None = None, params: RobotParams | None = None,
                 seed: int = 0, jump: int = 4000, delay: int = 25) -> None:
        if kind not in SENSOR_KINDS:
            raise FaultError(f"unknown sensor fault {kind!r}; known: {', '.join(SENSOR_KINDS)}")
        if int(start) < 0:
            raise FaultError(f"start must be >= 0, got {start!r}")
        if kind == "delay" and int(delay) < 1:
            raise FaultError(f"delay must be >= 1 tick, got {delay!r}")
        p = params or load_params()
        self.kind = kind
        self.start = int(start)
        self.stop = None if stop is None else int(stop)
        if self.stop is not None and self.stop <= self.start:
            raise FaultError(f"stop ({stop}) must be after start ({start})")
        self.adc_max = (1 << int(p.adc_bits)) - 1
        self.jump = int(jump)
        self.delay = int(delay)
        self._rng = random.Random(seed)
        self._hist: list[tuple[int, int]] = []
        self._stuck: int | None = None
        self.applied = 0

    def __call__(self, tick: int, adc: int, enc: int) -> tuple[int, int]:
        """The ``(adc, enc)`` the board gets at ``tick`` instead of the true one."""
        k = self.kind
        if k == "delay":
            self._hist.append((adc, enc))
            if len(self._hist) > self.delay + 1:
                self._hist.pop(0)
        if tick < self.start or (self.stop is not None and tick >= self.stop):
            if k == "enc_jump" and self.stop is not None and tick >= self.stop:
                return adc, (enc + self.jump) & 0xFFFF
            return adc, enc
        self.applied += 1
        if k == "adc_low":
            return 0, enc
        if k == "adc_high":
            return self.adc_max, enc
        if k == "adc_float":
            return self._rng.randint(0, self.adc_max), enc
        if k == "enc_stuck":
            if self._stuck is None:
                self._stuck = enc
            return adc, self._stuck
        if k == "enc_jump":
            return adc, (enc + self.jump) & 0xFFFF
        return self._hist[0]


class ActuatorFault:
    """From tick ``start`` the plant ignores the motor command (it gets duty 0).

    Parameters
    ----------
    start : int
        First tick affected.
    kind : {"dead", "stuck"}
        ``dead``: no force at all (open lead, driver off); ``stuck``: the duty of tick
        ``start - 1`` forever (a latched driver).
    """

    def __init__(self, start: int, kind: str = "dead") -> None:
        if kind not in ("dead", "stuck"):
            raise FaultError(f"actuator fault kind must be 'dead' or 'stuck', got {kind!r}")
        self.start = int(start)
        self.kind = kind
        self._last = 0
        self.ignored = 0

    def __call__(self, tick: int, duty: int) -> int:
        """The duty the plant actually applies at ``tick``."""
        if tick < self.start:
            self._last = duty
            return duty
        self.ignored += 1
        return 0 if self.kind == "dead" else self._last


# ---------------------------------------------------------------- accounting
class SeqAccount:
    """Accounts for the board's periodic frames by their serial sequence number.

    Telemetry (``telem_state`` + ``telem_ctrl``, one seq for the pair) and heartbeats share
    one counter on the board, incremented once per periodic event, so the seqs seen must be
    contiguous; a gap is a lost frame, a repeat a duplicate, a step back a reordered frame.

    Attributes
    ----------
    events : int
        Distinct periodic events seen.
    telemetry, heartbeats : int
        Distinct telemetry / heartbeat events seen.
    duplicates, reordered : int
        Frames seen again / seen after a later one.
    """

    def __init__(self) -> None:
        self._last: int | None = None
        self._first: int | None = None
        self._seen: dict[int, str] = {}
        self._pair: dict[int, int] = {}
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
            elif u < self._last:
                self.reordered += 1
        kind = "hb" if t is _HEARTBEAT else "tel"
        bit = 1 if t is _TELEM_STATE else 2 if t is _TELEM_CTRL else 4
        have = self._pair.get(u, 0)
        if have & bit:
            self.duplicates += 1
            return
        self._pair[u] = have | bit
        self._seen[u] = kind

    @property
    def events(self) -> int:
        return len(self._seen)

    @property
    def telemetry(self) -> int:
        return sum(1 for v in self._seen.values() if v == "tel")

    @property
    def heartbeats(self) -> int:
        return sum(1 for v in self._seen.values() if v == "hb")

    @property
    def span(self) -> int:
        """Events the seqs say were sent (first to last seen)."""
        return 0 if self._first is None else self._last - self._first + 1  # type: ignore[operator]

    @property
    def lost(self) -> int:
        """Periodic events missing between the first and the last seen."""
        return self.span - self.events

    @property
    def half_pairs(self) -> int:
        """Telemetry events of which only one of the two frames arrived."""
        return sum(1 for u, v in self._seen.items() if v == "tel" and self._pair[u] != 3)

    def stats(self) -> dict[str, int]:
        """All counters as a dict."""
        return {"seq_events": self.events, "seq_span": self.span, "seq_lost": self.lost,
                "telemetry": self.telemetry, "heartbeats": self.heartbeats, "duplicates": self.duplicates,
                "reordered": self.reordered, "half_pairs": self.half_pairs}


# ---------------------------------------------------------------- the lossy loop
@dataclass
class LossyRun:
    """A lockstep run over a faulty link (see :func:`run_lossy`).

    Attributes
    ----------
    log : dict of ndarray
        The plant log (:data:`sim.plantsim.LOG_COLUMNS`) plus per tick ``fw_state``,
        ``fw_faults`` (of the last answer received, -1 before any), ``answered`` (1 if the
        answer for this tick arrived in time), ``duty_fw`` (the duty the board commanded,
        held when lost) and ``adc_sent``, ``enc_sent`` (what was sent).
    stats : dict
        ``ticks``, ``answered``, ``lost``, ``stale`` (answers that came too late or for a
        tick not sent now), ``bad_tick`` (answers for a tick never sent: must stay 0),
        ``host_drops`` (the host decoder's counters), the :class:`SeqAccount` stats,
        ``nacks`` (list of str) and ``replies`` (``(tick, message)`` of every ACK, NACK and
        PARAM_VALUE received during the run).
    """

    log: dict[str, np.ndarray]
    stats: dict[str, Any] = field(default_factory=dict)


def run_lossy(session: HilSession, scenario: Scenario, params: RobotParams | None = None, *,
              sensor: Callable[[int, int, int], tuple[int, int]] | None = None,
              actuator: Callable[[int, int], int] | None = None, answer_timeout: float = 0.02,
              seed: int | None = None, x0: Sequence[float] | None = None,
              on_tick: Callable[[int], None] | None = None, prepare: bool = True) -> LossyRun:
    """Run a scenario in lockstep over a link that may lose, corrupt or reorder frames.

    Parameters
    ----------
    session : HilSession
        An open lockstep session (its fault hooks, if any, act on every frame).
    scenario : Scenario
        The scenario.
    params : RobotParams, optional
        Robot parameters (default ``sim/robot.toml``).
    sensor : callable, optional
        ``sensor(tick, adc, enc) -> (adc, enc)``, e.g. a :class:`SensorFault`.
    actuator : callable, optional
        ``actuator(tick, duty) -> duty`` the plant applies, e.g. an :class:`ActuatorFault`.
    answer_timeout : float
        Seconds to wait for the answer of a tick before holding the previous duty.
    seed, x0
        As for :meth:`host.hil.session.HilSession.run_lockstep`.
    on_tick : callable, optional
        ``on_tick(k)`` before tick ``k`` is sent (to cut the link, ...).
    prepare : bool
        Bring the board to a clean armed start first (:meth:`HilSession.prepare`); with
        ``False`` the board is taken as it is.

    Returns
    -------
    LossyRun
    """
    if session.mode != "lockstep":
        raise HilError("run_lossy needs a lockstep session")
    if not answer_timeout > 0:
        raise FaultError(f"answer_timeout must be > 0, got {answer_timeout!r}")
    link = session._link()
    params = params or load_params()
    sim = PlantSim(params, scenario, seed=seed, x0=x0)
    acc = SeqAccount()
    if prepare:
        session.prepare(sim)
    # python-can's serial interface ignores recv()'s timeout and waits for its port's read
    # timeout (0.1 s) instead: shorten it for the run, or each lost answer costs 0.1 s
    port = getattr(getattr(link, "bus", None), "_ser", None) if isinstance(link, CanLink) else None
    old_timeout = port.timeout if port is not None else None
    if port is not None:
        port.timeout = answer_timeout
    try:
        return _lossy_loop(session, link, sim, scenario, acc, sensor, actuator, answer_timeout, on_tick)
    finally:
        if port is not None:
            port.timeout = old_timeout


def _lossy_loop(session: HilSession, link: Any, sim: PlantSim, scenario: Scenario, acc: SeqAccount,
                sensor: Callable[[int, int, int], tuple[int, int]] | None,
                actuator: Callable[[int, int], int] | None, answer_timeout: float,
                on_tick: Callable[[int], None] | None) -> LossyRun:
    nacks: list[str] = []
    replies: list[tuple[int, Any]] = []
    n = sim.n_ticks
    fw_state = np.full(n, -1, dtype=np.int64)
    fw_faults = np.full(n, -1, dtype=np.int64)
    answered = np.zeros(n, dtype=np.int64)
    duty_fw = np.zeros(n, dtype=np.int64)
    adc_s = np.zeros(n, dtype=np.int64)
    enc_s = np.zeros(n, dtype=np.int64)
    duty = 0
    st, fl = -1, -1
    stale = bad_tick = 0
    ref_prev = sim.x_ref()
    for k in range(n):
        if on_tick is not None:
            on_tick(k)
        adc, enc = sim.read()
        if sensor is not None:
            adc, enc = sensor(k, adc, enc)
        ref = float(scenario.x_ref(k * sim.Ts))
        if ref != ref_prev:
            link.send(_SET_REF(x_um=int(round(ref * 1e6))))
            ref_prev = ref
        link.send(_SENSOR(tick=k, adc=int(adc), enc=int(enc)))
        adc_s[k], enc_s[k] = adc, enc
        deadline = time.monotonic() + answer_timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            try:
                m = link.recv(left)
            except LinkError as exc:
                session._check_board()
                raise HilError(f"link failed at tick {k}: {exc}") from exc
            if m is None:
                break
            if type(m) is _ACTUATOR:
                if m.tick == k:
                    answered[k] = 1
                    duty, st, fl = m.duty, m.state, m.faults
                    break
                if 0 <= m.tick < k:
                    stale += 1
                else:
                    bad_tick += 1
                continue
            acc.add(m, link.last_seq)
            if type(m).NAME == "nack":
                nacks.append(f"tick {k}: {m}")
                replies.append((k, m))
            elif type(m).NAME in ("ack", "param_value"):
                replies.append((k, m))
        fw_state[k], fw_faults[k], duty_fw[k] = st, fl, duty
        sim.step(actuator(k, duty) if actuator is not None else duty)
    # collect what is still in flight
    end = time.monotonic() + 0.05
    while (left := end - time.monotonic()) > 0:
        m = link.recv(left)
        if m is None:
            break
        if type(m) is _ACTUATOR:
            stale += 1
        else:
            acc.add(m, link.last_seq)
    log = sim.result()
    log.update(fw_state=fw_state, fw_faults=fw_faults, answered=answered, duty_fw=duty_fw,
               adc_sent=adc_s, enc_sent=enc_s)
    stats: dict[str, Any] = {"ticks": n, "answered": int(answered.sum()), "lost": int(n - answered.sum()),
                             "stale": stale, "bad_tick": bad_tick, "host_drops": dict(link.drops),
                             "nacks": nacks, "replies": replies}
    stats.update(acc.stats())
    return LossyRun(log, stats)


def stream_realtime(session: HilSession, seconds: float, *, adc: int, enc: int = 0, start_tick: int = 0,
                    at: Sequence[tuple[float, Callable[[], None]]] = ()) -> int:
    """Stream a constant sensor reading to a real-time board for ``seconds`` (wall clock).

    The board paces itself; the host sends one ``hil_sensor`` frame per loop period and a
    reader thread drains whatever comes back (record it with a :class:`Tap` as the
    session's ``fault_rx`` hook).  ``at`` lists ``(t, action)`` pairs: ``action()`` is
    called once ``t`` seconds into the stream (cut the link, restore it...).  This is the
    bare minimum a link-loss test needs -- no plant, so nothing can fall and trip another
    fault -- and it does not depend on :meth:`HilSession.run_realtime`.

    Returns
    -------
    int
        The next tick number.
    """
    import threading

    if session.mode != "realtime":
        raise HilError("stream_realtime needs a real-time session")
    link = session._link()
    period = 1.0 / int(load_params().rate)
    stop = threading.Event()
    errors: list[BaseException] = []

    def reader() -> None:
        while not stop.is_set():
            try:
                link.recv(0.02)
            except LinkError as exc:  # pragma: no cover - reported below
                errors.append(exc)
                return
            except Exception as exc:  # noqa: BLE001 - python-can on a half-read frame
                errors.append(exc)
                return

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    actions = sorted(at, key=lambda a: a[0])
    t0 = time.perf_counter()
    k = start_tick
    try:
        while True:
            now = time.perf_counter() - t0
            if now >= seconds:
                break
            while actions and actions[0][0] <= now:
                actions.pop(0)[1]()
            link.send(_SENSOR(tick=k & 0x3FFFFFFF, adc=int(adc), enc=int(enc) & 0xFFFF))
            k += 1
            nxt = t0 + (k - start_tick) * period
            while (left := nxt - time.perf_counter()) > 0:
                time.sleep(left if left < 0.001 else left - 0.0005)
    finally:
        stop.set()
        th.join(1.0)
    if errors:
        raise HilError(f"receive failed while streaming: {errors[0]}")
    return k


# ---------------------------------------------------------------- a link on a bare fd
class FdPort:
    """The pyserial surface :class:`host.link.clients.SerialLink` uses, over an open file descriptor.

    A host process that crashes leaves the line (the board's USB port, here the pty master
    held by the test) as it was; a new host process gets the line again.  ``FdPort`` lets a
    link be made on such an inherited or kept descriptor (see :func:`serial_link_on_fd`).

    Parameters
    ----------
    fd : int
        Open descriptor (not closed by :meth:`close` unless ``own=True``).
    own : bool
        Close ``fd`` on :meth:`close`.
    """

    def __init__(self, fd: int, *, own: bool = False) -> None:
        self.fd = int(fd)
        self.own = bool(own)
        self.timeout: float | None = 0.0
        self.is_open = True

    def fileno(self) -> int:
        return self.fd

    @property
    def in_waiting(self) -> int:
        import fcntl
        import struct
        import termios

        return struct.unpack("i", fcntl.ioctl(self.fd, termios.FIONREAD, b"\0\0\0\0"))[0]

    def read(self, size: int = 1) -> bytes:
        import os
        import select

        t = self.timeout
        r, _, _ = select.select([self.fd], [], [], t)
        if not r:
            return b""
        try:
            return os.read(self.fd, size)
        except BlockingIOError:
            return b""

    def write(self, data: bytes) -> int:
        import os
        import select

        view = memoryview(bytes(data))
        while view:
            select.select([], [self.fd], [], 1.0)
            try:
                n = os.write(self.fd, view)
            except BlockingIOError:
                continue
            view = view[n:]
        return len(data)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        import os

        if self.is_open and self.own:
            os.close(self.fd)
        self.is_open = False


def serial_link_on_fd(fd: int, *, own: bool = False) -> SerialLink:
    """A :class:`host.link.clients.SerialLink` on an already open descriptor (see :class:`FdPort`)."""
    link = SerialLink("loop://")
    link._ser.close()
    link._ser = FdPort(fd, own=own)
    link.url = f"fd:{fd}"
    return link


# ---------------------------------------------------------------- the probed virtual board
_PROBE = r"""
import sys, gc, micropython
from firmware import main_hil
from firmware.uart_unix import UnixUART


def go():
    u = UnixUART(%(port)r)
    m = main_hil.HilMain(u, %(link)r, %(mode)r, %(node)d)
    gc.collect()
    a0 = gc.mem_alloc()
    lock = %(lock)r
    if lock:
        micropython.heap_lock()
    else:
        gc.disable()
    try:
        rc = m.run()
    finally:
        if lock:
            micropython.heap_unlock()
    a1 = gc.mem_alloc()
    d = m.dec
    out = "UPRIGHT-PROBE alloc0=%%d alloc1=%%d locked=%%d steps=%%d frames=%%d" %% (a0, a1, lock, m.n_steps, m.n_frames)
    for k in ("n_ok", "n_crc", "n_length", "n_unknown", "n_overrun", "n_framing", "n_other"):
        if hasattr(d, k):
            out += " %%s=%%d" %% (k, getattr(d, k))
    out += " refused=%%d handled=%%d" %% (m.disp.n_refused, m.disp.n_handled)
    print(out)
    return rc


sys.exit(go())
"""

_PROBE_RE = re.compile(r"UPRIGHT-PROBE (.*)")


class ProbeSession(HilSession):
    """A virtual-board :class:`~host.hil.session.HilSession` whose firmware reports its heap and drops.

    The firmware is the unchanged :class:`firmware.main_hil.HilMain`; the wrapper around it
    (the MicroPython source in this module) holds ``micropython.heap_lock()`` for the whole
    run in lockstep mode -- one allocation anywhere in the loop, the decoder or the command
    handler would end the firmware with ``MemoryError`` -- and, in real-time mode, disables
    the GC instead and reports the growth.  At exit it prints ``gc.mem_alloc()`` before and
    after the run, the steps and frames handled, and the decoder's drop counters; read them
    with :meth:`probe` after :meth:`close`.
    """

    def __init__(self, *, link: str = "serial", mode: str = "lockstep", node: int = 1, **kw: Any) -> None:
        if kw.get("port") is not None:
            raise FaultError("ProbeSession runs the virtual board only (port=None)")
        kw.pop("port", None)
        super().__init__(None, link=link, mode=mode, node=node, **kw)
        self._probe_out = ""

    def _board_code(self, slave: str) -> str:
        """The probe wrapper around the unchanged HIL main (see the class docstring)."""
        return _PROBE % {"port": slave, "link": self.link_kind, "mode": self.mode, "node": self.node,
                         "lock": self.mode == "lockstep"}

    def close(self) -> None:
        """Close the link, let the firmware print its report and stop it."""
        board = self.board
        super().close()
        if board is not None:
            self._probe_out = board.output()
            self.returncode = board.returncode

    def probe(self) -> dict[str, int]:
        """The firmware's exit report (after :meth:`close`).

        Raises
        ------
        HilError
            If the firmware did not report (it crashed: e.g. ``MemoryError`` under the
            heap lock); the message holds its output tail.
        """
        m = _PROBE_RE.search(self._probe_out)
        if m is None:
            tail = " | ".join(self._probe_out.strip().splitlines()[-4:])
            raise HilError(f"the firmware did not report at exit: {tail or '(no output)'}")
        return {k: int(v) for k, v in (kv.split("=") for kv in m.group(1).split())}

