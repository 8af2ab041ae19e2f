"""The real-time HIL loop: the firmware paces itself, the host streams one sensor frame per period.

The firmware paces its own loop at the loop rate with ``ticks_us``; the host streams one
sensor frame per period on its own clock, phase-locked so that frames arrive about half a
period before the firmware's tick, and steps the plant with the duty received for that
tick (or the previous one if it is late, counted as ``late``).  The host measures the
sensor-to-actuator latency of every tick and the jitter of the answers' spacing, and reads
the firmware's own ``timing`` statistics (step time, longest period, overruns) at the end.
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from firmware import msgtable as T
from host.boards.vport import set_realtime, steal_seconds
from host.hil.accounting import Sink
from host.hil.errors import HilError
from host.hil.lockstep import PRIME_TICK
from host.hil.results import HilRun
from host.link import messages as M
from sim.params import RobotParams, load_params
from sim.plantsim import PlantSim
from sim.scenario import Scenario

__all__ = ["run_realtime"]

_ACTUATOR = M.BY_NAME["hil_actuator"]


def _sleep_until(t: float) -> None:
    # sleep most of the wait, spin the last 0.3 ms (the host's own pacing jitter)
    while True:
        left = t - time.perf_counter()
        if left <= 0:
            return
        if left > 0.0006:
            time.sleep(left - 0.0004)


class _PhaseLock:
    # steer the host's send times so that a frame arrives about `lead` of a period before
    # the firmware's tick.  An answer's latency = the frame's wait for the tick + the step
    # + the link, so aiming the latency at lead * T puts the wait near lead * T: when
    # answers come later than that, the frames waited too long -- send later; earlier --
    # send earlier.  Both sides use the same monotonic clock, so once locked it holds.
    def __init__(self, T_s: float, lead: float) -> None:
        self.T = T_s
        self.target = lead * T_s
        self._err = 0.0
        self._n = 0

    def observe(self, latency: float) -> None:
        # latency in s; wrap it into one period around the target
        e = latency - self.target
        self._err = 0.7 * self._err + 0.3 * e if self._n else e
        self._n += 1

    def correction(self) -> float:
        # shift the next send later when answers come late (frames waited too long)
        c = max(-0.1 * self.T, min(0.1 * self.T, 0.3 * self._err))
        self._err -= c
        return c


def run_realtime(session: Any, scenario: Scenario, params: RobotParams | None = None, *, lead: float = 0.5,
                 sync_ticks: int = 100, progress: Callable[[int, int], None] | None = None,
                 seed: int | None = None, x0: Sequence[float] | None = None,
                 fw_params: Mapping[str | int, int] | None = None) -> HilRun:
    """Run one scenario in real time on an open real-time session.

    See :meth:`host.hil.session.HilSession.run_realtime` (which calls it) for the parameters.
    """
    if session.mode != "realtime":
        raise HilError("this session's firmware runs in lockstep mode; use run_lockstep")
    if not 0.05 <= lead <= 0.9:
        raise ValueError(f"lead must be in [0.05, 0.9] of a period, got {lead!r}")
    params = params or load_params()
    sim = PlantSim(params, scenario, seed=seed, x0=x0)
    link = session._link()
    sink = Sink(link)
    # armed later, in the stream, once the phase is locked on the initial reading
    session.prepare(sim, sink, arm=False, fw_params=fw_params)
    rt = session.rt_priority
    host_rt = set_realtime(rt - 1) if rt and rt > 1 else False
    try:
        return _Stream(session, sim, sink, lead).run(sync_ticks, progress, host_rt)
    finally:
        if host_rt:
            set_realtime(None)


class _Stream:
    # one real-time run: the phase lock, the answers' bookkeeping, the per-tick records
    def __init__(self, session: Any, sim: PlantSim, sink: Sink, lead: float) -> None:
        self.session = session
        self.link = session._link()
        self.sim = sim
        self.sink = sink
        self.n = n = sim.n_ticks
        self.T_s = sim.Ts
        self.fw_state = np.zeros(n, dtype=np.int64)
        self.fw_faults = np.zeros(n, dtype=np.int64)
        self.latency = np.full(n, np.nan)
        self.late = np.zeros(n, dtype=np.int64)
        self.send_t: dict[int, float] = {}
        self.pll = _PhaseLock(self.T_s, lead)
        # ARM (sent in the stream) carries the board's arming epoch, read after prepare()
        self.epoch = session._request(self.link.query, "session").token

    def pump(self, until: float, want: int | None) -> Any:
        # receive until `until` (or the answer for tick `want`); returns that answer
        clock, link, send_t, n = time.perf_counter, self.link, self.send_t, self.n
        got = None
        while True:
            left = until - clock()
            if left <= 0:
                return got
            m = link.recv(min(left, 0.0005) if got is None else 0.0)
            if m is None:
                if got is not None:
                    return got
                continue
            now = clock()
            if type(m) is _ACTUATOR:
                ts = send_t.pop(m.tick, None)
                if ts is not None:
                    self.pll.observe(now - ts)
                    if 0 <= m.tick < n:
                        self.latency[m.tick] = (now - ts) * 1e6
                if want is not None and m.tick == want:
                    got = m
                    if until - clock() > 0:
                        return got
            else:
                self.sink.other(m, want if want is not None else -1)

    def run(self, sync_ticks: int, progress: Callable[[int, int], None] | None, host_rt: bool) -> HilRun:
        sess, sim, link, n, T_s = self.session, self.sim, self.link, self.n, self.T_s
        clock = time.perf_counter
        send_t, pll, pump = self.send_t, self.pll, self.pump
        fw_state, fw_faults, late = self.fw_state, self.fw_faults, self.late
        adc0, enc0 = sim.read()
        t_next = clock() + 0.01
        # phase lock on the resting initial reading (disarmed, duty 0)
        for i in range(sync_ticks):
            _sleep_until(t_next)
            tick = (PRIME_TICK - sync_ticks + i) & PRIME_TICK
            send_t[tick] = clock()
            sess._sensor(tick, adc0, enc0)
            pump(t_next + T_s * 0.9, None)
            t_next += T_s + pll.correction()
        send_t.clear()
        # start the firmware's timing statistics afresh (its TIMING reply resets them)
        # and arm, both in the stream: the scenario's first frame follows
        link.send(M.BY_NAME["request"](msg_id=T.TIMING))
        link.send(M.BY_NAME["arm"](epoch=self.epoch))
        t0 = clock()
        steal0 = steal_seconds()
        ref_prev = sim.x_ref()
        x_ref_at = sim.scenario.x_ref
        duty = 0
        for k in range(n):
            _sleep_until(t_next)
            ref = float(x_ref_at(k * sim.Ts))
            if ref != ref_prev:
                sess._set_ref(ref)
                ref_prev = ref
            send_t[k] = clock()
            sess._sensor(k, *sim.read())
            a = pump(t_next + T_s * 0.85, k)
            if a is None:
                late[k] = 1
            else:
                duty = a.duty
                fw_state[k] = a.state
                fw_faults[k] = a.faults
            if k and a is None:
                fw_state[k] = fw_state[k - 1]
                fw_faults[k] = fw_faults[k - 1]
            sim.step(duty)
            t_next += T_s + pll.correction()
            if progress is not None and k % 250 == 0:
                progress(k, n)
            if sess.board is not None and k % 500 == 0:
                sess._check_board()
        wall = clock() - t0
        steal = steal_seconds() - steal0
        if progress is not None:
            progress(n, n)
        pump(clock() + 0.02, None)
        stats = sess.finish()
        self.sink.drain(link, n)
        log = sim.result()
        log.update(fw_state=fw_state, fw_faults=fw_faults, latency_us=self.latency, late=late)
        stats.update(self.sink.stats())
        lat = self.latency[np.isfinite(self.latency)]
        stats.update({
            "ticks": n,
            "gains": sess.gains,
            "late": int(late.sum()),
            "answered": int(lat.size),
            "latency_us_mean": float(lat.mean()) if lat.size else math.nan,
            "latency_us_max": float(lat.max()) if lat.size else math.nan,
            "latency_us_p99": float(np.percentile(lat, 99)) if lat.size else math.nan,
            "period_us": T_s * 1e6,
            "wall_s": wall,
            "steal_s": steal,
            "fw_realtime_policy": bool(sess.board.realtime_policy) if sess.board is not None else None,
            "host_realtime_policy": host_rt,
        })
        return HilRun(sim.scenario, sim.params, log, "realtime", sess.link_kind, wall, stats)
