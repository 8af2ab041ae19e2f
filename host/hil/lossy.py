"""Lockstep over a link that loses, corrupts or reorders frames, and a bare real-time stream.

:func:`run_lossy` runs THE lockstep loop (:class:`host.hil.lockstep.Lockstep`) in its lossy
form, the way a real loop survives a lossy link: the plant advances every tick; if the
board's answer for the tick does not come within ``answer_timeout`` the previous duty is
held (the PWM keeps its last value) and the tick is counted lost; stale answers are
discarded.  It accounts for every periodic frame (telemetry, heartbeat) by its sequence
number (:class:`host.hil.accounting.SeqAccount`).  Sensor and actuator faults
(:mod:`host.hil.faults`) plug into the loop's hooks.

:func:`stream_realtime` streams a constant reading to a real-time board, with actions at
given times (cut the link, restore it): the bare minimum a link-loss test needs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from host.hil.accounting import Sink
from host.hil.errors import HilError
from host.hil.faults import FaultError
from host.hil.lockstep import Lockstep
from host.hil.session import HilSession
from host.link import messages as M
from host.link.clients import CanLink, LinkError
from sim.params import RobotParams, load_params
from sim.plantsim import PlantSim
from sim.scenario import Scenario

__all__ = ["LossyRun", "run_lossy", "stream_realtime"]

_SENSOR = M.BY_NAME["hil_sensor"]


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
        ``host_drops`` (the host decoder's counters), the :class:`~host.hil.accounting.SeqAccount` stats,
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
        ``sensor(tick, adc, enc) -> (adc, enc)``, e.g. a :class:`host.hil.faults.SensorFault`.
    actuator : callable, optional
        ``actuator(tick, duty) -> duty`` the plant applies, e.g. an :class:`host.hil.faults.ActuatorFault`.
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
    if prepare:
        session.prepare(sim)
    # python-can's serial interface ignores recv()'s timeout and waits for its port's read
    # timeout (0.1 s) instead: shorten it for the run, or each lost answer costs 0.1 s
    port = getattr(getattr(link, "bus", None), "_ser", None) if isinstance(link, CanLink) else None
    old_timeout = port.timeout if port is not None else None
    if port is not None:
        port.timeout = answer_timeout
    try:
        return _lossy(session, link, sim, sensor, actuator, answer_timeout, on_tick)
    finally:
        if port is not None:
            port.timeout = old_timeout


def _lossy(session: HilSession, link: Any, sim: PlantSim,
           sensor: Callable[[int, int, int], tuple[int, int]] | None,
           actuator: Callable[[int, int], int] | None, answer_timeout: float,
           on_tick: Callable[[int], None] | None) -> LossyRun:
    sink = Sink(link, strict=False)
    loop = Lockstep(session, sim, sink=sink, depth=0, answer_timeout=answer_timeout, on_tick=on_tick,
                    sensor=sensor, actuator=actuator).run()
    # collect what is still in flight
    loop.drain(0.05)
    n = loop.n
    answered = int(loop.answered.sum())
    log = loop.log("fw_state", "fw_faults", "answered", "duty_fw", "adc_sent", "enc_sent")
    stats: dict[str, Any] = {"ticks": n, "answered": answered, "lost": n - answered,
                             "stale": loop.stale, "bad_tick": loop.bad_tick, "host_drops": dict(link.drops),
                             "nacks": list(sink.nacks), "replies": list(sink.replies)}
    stats.update(sink.acct.stats())
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
