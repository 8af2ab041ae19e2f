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
    :class:`Tap` records what the host received.
sensors
    :class:`SensorFault` transforms the ``(adc, enc)`` reading the plant produced before it
    is sent: ADC at a rail, ADC floating (uniform noise over the whole range), encoder
    stuck, encoder jumping, readings delayed by extra ticks -- the ``sensor`` hook of the
    lockstep loop (:class:`host.hil.lockstep.Lockstep`).
actuator
    :class:`ActuatorFault`: from a given tick the plant ignores the motor command (a dead
    driver or an open motor lead) -- the loop's ``actuator`` hook.

The loop that survives a lossy link, :func:`host.hil.lossy.run_lossy`, runs them.
"""

from __future__ import annotations

import math
import random
import time
from typing import Any, Callable

from host.link import messages as M
from sim.params import RobotParams, load_params

__all__ = [
    "FaultError",
    "FrameFaults",
    "StreamFaults",
    "BusFaults",
    "Tap",
    "SensorFault",
    "ActuatorFault",
    "SENSOR_KINDS",
]

SENSOR_KINDS = ("adc_low", "adc_high", "adc_float", "enc_stuck", "enc_jump", "delay")
"""Sensor faults :class:`SensorFault` can inject."""


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
