"""THE lockstep loop: sensor frames kept ahead of the board, one answer per tick, the plant stepped.

For tick k the host sends the ``hil_sensor`` frame (tick k, ADC counts, encoder counter),
the firmware runs exactly one ``app.step()`` and answers ``hil_actuator`` (tick k, duty,
state, faults); the plant (:class:`sim.plantsim.PlantSim`) integrates that duty for one
period.  Reference changes go out as ``set_reference`` frames just before the tick they
apply to; every other message the board sends (telemetry, heartbeats, acks) goes to a
:class:`~host.hil.accounting.Sink`.

Pipelining: the reading the board gets at tick k+j (j <= the measurement delay in ticks,
5 at 10 ms / 500 Hz) was taken at tick k+j-delay <= k, so it is already known while the
board works on tick k (:meth:`sim.plantsim.PlantSim.peek`).  The loop therefore keeps up to
``depth`` sensor frames in flight, which lets the host's plant and the firmware run on two
cores at once.  The firmware still handles one frame after the other, so this changes
nothing in what it computes.

Two ways to treat a missing answer:

strict (``answer_timeout=None``; :meth:`host.hil.session.HilSession.run_lockstep`, the soak)
    Every answer must carry the tick just sent -- a lost or repeated tick raises
    :class:`~host.hil.errors.TickError`; no answer within the session's timeout raises
    :class:`~host.hil.errors.HilError`.  The run is bit-identical across runs and links.
lossy (``answer_timeout=seconds``; :func:`host.hil.lossy.run_lossy`)
    The plant advances every tick; if the answer for the tick does not come in time the
    previous duty is held (the PWM keeps its last value) and the tick is counted lost;
    stale answers (an earlier tick) and answers for a tick never sent are counted.

Hooks (all optional) let the callers reuse the one loop:

``on_tick(tick)``
    before the frame of ``tick`` is sent (cut the link, start faults...);
``sensor(tick, adc, enc) -> (adc, enc)``
    transforms the reading before it is sent (sensor fault injection);
``actuator(tick, duty) -> duty``
    the duty the plant actually applies (actuator fault injection);
``after_tick(tick, answer)``
    after the plant stepped (``answer`` is the ``hil_actuator`` message, ``None`` if lost):
    per-tick or per-chunk bookkeeping (the soak's chunks);
``progress(tick, n_ticks)``
    every 250 ticks and at the end.
"""

from __future__ import annotations

import time
from typing import Any, Callable

import numpy as np

from firmware.supervisor import BALANCING
from host.hil.accounting import Sink
from host.hil.errors import HilError, TickError
from host.link import messages as M
from host.link.clients import LinkError
from sim.plantsim import PlantSim

__all__ = ["Lockstep", "PRIME_TICK"]

PRIME_TICK = (1 << 30) - 1
"""Tick number of the priming sensor frame sent before each scenario (outside any scenario's range;
also the mask of the 30-bit tick field)."""

_SENSOR = M.BY_NAME["hil_sensor"]
_ACTUATOR = M.BY_NAME["hil_actuator"]
_SET_REF = M.BY_NAME["set_reference"]
_BALANCING = BALANCING  # the only state with the driver enabled (App._drive)


class Lockstep:
    """The lockstep loop of one scenario over an open, prepared session's link.

    Parameters
    ----------
    session : HilSession
        An open lockstep session (its ``link``, ``timeout`` and ``board`` are used; the
        caller has run :meth:`~host.hil.session.HilSession.prepare`).
    sim : PlantSim
        The plant, at its first tick.
    sink : Sink, optional
        Receives every message that is not an answer (default: a strict sink on the link).
    depth : int
        Sensor frames kept in flight, ``0 <= depth <= sim.sensor_model.delay_steps``.
    answer_timeout : float, optional
        ``None``: strict (see the module docstring); seconds: lossy.
    on_tick, sensor, actuator, after_tick, progress : callable, optional
        The hooks (see the module docstring).
    record : bool
        Keep per-tick arrays (``fw_state``, ``fw_faults``, ``answered``, ``duty_fw``,
        ``adc_sent``, ``enc_sent``); ``False`` for very long runs (the soak keeps its own).

    Attributes
    ----------
    fw_state, fw_faults : ndarray
        State and faults of the last answer received by each tick (-1 before any).
    answered : ndarray
        1 where the answer for the tick arrived (in time).
    duty_fw : ndarray
        The duty the board commanded for the tick (held when lost).
    adc_sent, enc_sent : ndarray
        What was sent for the tick (after the ``sensor`` hook).
    stale, bad_tick : int
        Lossy: answers for an earlier tick / for a tick never sent.
    t_plant, t_link, wall : float
        Seconds in the plant, waiting on the link, and the whole loop.
    """

    def __init__(self, session: Any, sim: PlantSim, *, sink: Sink | None = None, depth: int = 0,
                 answer_timeout: float | None = None,
                 on_tick: Callable[[int], None] | None = None,
                 sensor: Callable[[int, int, int], tuple[int, int]] | None = None,
                 actuator: Callable[[int, int], int] | None = None,
                 after_tick: Callable[[int, Any], None] | None = None,
                 progress: Callable[[int, int], None] | None = None, record: bool = True) -> None:
        d = sim.sensor_model.delay_steps
        if not 0 <= int(depth) <= d:
            raise ValueError(f"depth must be in 0..{d} (the measurement delay in ticks), got {depth!r}")
        if answer_timeout is not None and not answer_timeout > 0:
            raise ValueError(f"answer_timeout must be > 0, got {answer_timeout!r}")
        self.session = session
        self.link = session.link
        if self.link is None:
            raise HilError("session is not open")
        self.sim = sim
        self.sink = sink if sink is not None else Sink(self.link)
        self.depth = int(depth)
        self.answer_timeout = answer_timeout
        self.on_tick, self.sensor, self.actuator = on_tick, sensor, actuator
        self.after_tick, self.progress = after_tick, progress
        self.n = n = sim.n_ticks
        self.record = bool(record)
        size = n if record else 0
        self.fw_state = np.full(size, -1, dtype=np.int64)
        self.fw_faults = np.full(size, -1, dtype=np.int64)
        self.answered = np.zeros(size, dtype=np.int64)
        self.duty_fw = np.zeros(size, dtype=np.int64)
        self.adc_sent = np.zeros(size, dtype=np.int64)
        self.enc_sent = np.zeros(size, dtype=np.int64)
        self.stale = 0
        self.bad_tick = 0
        self.t_plant = 0.0
        self.t_link = 0.0
        self.wall = 0.0

    # ------------------------------------------------------------------ the loop
    def run(self) -> "Lockstep":
        """Run every tick of the scenario; returns ``self`` (the records are attributes)."""
        sim, n, depth = self.sim, self.n, self.depth
        send = self.link.send
        on_tick, sensor, actuator = self.on_tick, self.sensor, self.actuator
        after_tick, progress, rec = self.after_tick, self.progress, self.record
        wait = self._wait_strict if self.answer_timeout is None else self._wait_lossy
        x_ref_at = sim.scenario.x_ref
        Ts = sim.Ts
        clock = time.perf_counter
        ref_prev = sim.x_ref()
        duty, st, fl = 0, -1, -1
        sent = 0
        t0 = clock()
        for k in range(n):
            # keep `depth` frames ahead of the board (readings already determined)
            c0 = cs = clock()
            while sent < n and sent - k <= depth:
                if on_tick is not None:
                    on_tick(sent)
                j = sent - k
                adc, enc = sim.read() if j == 0 else sim.peek(j)
                if sensor is not None:
                    adc, enc = sensor(sent, adc, enc)
                ref = float(x_ref_at(sent * Ts))
                self.t_plant += clock() - c0
                if ref != ref_prev:
                    send(_SET_REF(x_um=int(round(ref * 1e6))))
                    ref_prev = ref
                send(_SENSOR(tick=sent, adc=int(adc), enc=int(enc)))
                if rec:
                    self.adc_sent[sent], self.enc_sent[sent] = adc, enc
                sent += 1
                c0 = clock()
            m = wait(k)
            c2 = clock()
            if m is not None:
                duty, st, fl = m.duty, m.state, m.faults
            if rec:
                self.fw_state[k], self.fw_faults[k], self.duty_fw[k] = st, fl, duty
                self.answered[k] = m is not None
            # the board enables its driver only while balancing (App._drive): EN low otherwise,
            # the bridge's outputs off and the motor coasting, as on the emulated board's pins
            sim.step(actuator(k, duty) if actuator is not None else duty, driven=1.0 if st == _BALANCING else 0.0)
            self.t_plant += clock() - c2
            self.t_link += c2 - cs
            if after_tick is not None:
                after_tick(k, m)
            if progress is not None and k % 250 == 0:
                progress(k, n)
        self.wall = clock() - t0
        if progress is not None:
            progress(n, n)
        return self

    def _fail(self, k: int, exc: LinkError) -> HilError:
        self.session._check_board()
        return HilError(f"link failed at tick {k}: {exc}")

    def _wait_strict(self, k: int) -> Any:
        # the next answer, which must be tick k's; other messages go to the sink
        recv, timeout = self.link.recv, self.session.timeout
        deadline = time.perf_counter() + timeout
        while True:
            try:
                # heartbeats keep coming while the firmware waits: bound the whole wait
                m = recv(max(0.0, deadline - time.perf_counter()))
            except LinkError as exc:
                raise self._fail(k, exc) from exc
            if m is None:
                self.session._check_board()
                raise HilError(f"no answer from the firmware for tick {k} within {timeout:g} s")
            if type(m) is _ACTUATOR:
                break
            self.sink.other(m, k)
        if m.tick != k:
            what = "repeated" if m.tick < k else "lost"
            raise TickError(f"tick {k}: the firmware answered tick {m.tick} (tick {min(k, m.tick)} {what})")
        return m

    def _wait_lossy(self, k: int) -> Any:
        # tick k's answer if it comes in time, else None; stale answers are counted
        recv = self.link.recv
        deadline = time.monotonic() + self.answer_timeout  # type: ignore[operator]
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            try:
                m = recv(left)
            except LinkError as exc:
                raise self._fail(k, exc) from exc
            if m is None:
                return None
            if type(m) is _ACTUATOR:
                if m.tick == k:
                    return m
                if 0 <= m.tick < k:
                    self.stale += 1
                else:
                    self.bad_tick += 1
                continue
            self.sink.other(m, k)

    # ------------------------------------------------------------------ after the loop
    def drain(self, seconds: float) -> None:
        """Collect what is still in flight for up to ``seconds``: answers count as stale,
        the rest goes to the sink."""
        recv = self.link.recv
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            m = recv(left)
            if m is None:
                break
            if type(m) is _ACTUATOR:
                self.stale += 1
            else:
                self.sink.other(m, self.n)

    def log(self, *columns: str) -> dict[str, np.ndarray]:
        """The plant's log (:meth:`sim.plantsim.PlantSim.result`) plus the named per-tick records."""
        out = self.sim.result()
        for c in columns:
            out[c] = getattr(self, c)
        return out
