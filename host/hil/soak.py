"""Soak: a long lockstep HIL run that must leave no trace in the firmware.

``upright soak --sim-seconds 3600 [--link serial|can]`` (``make soak``) balances the
robot through the report's square-wave reference (0 <-> 20 cm, 4.4 s period) for the given
simulated time, with the real firmware under the MicroPython unix port on a pty, one plant
and one armed, balancing board from start to end, and checks:

heap
    the firmware runs under ``micropython.heap_lock()`` for the whole run
    (the probed virtual board, ``HilSession(probe=True)``, :func:`host.boards.vport.probe_code`):
    one allocation would end it with ``MemoryError``;
    at exit it reports ``gc.mem_alloc()`` before and after, which must be equal.  (The board
    does not expose ``gc.mem_free()`` over the link -- there is no message for it -- so this
    is read from the virtual board's exit report.)
timing drift
    the board's uptime (from heartbeats requested at the start and the end) must advance
    by exactly one loop period per tick; its step time (telemetry ``step_us``, median per chunk)
    must not grow from chunk to chunk.
accounting
    every tick answered with its own tick number (a lost or repeated tick stops the run);
    every telemetry frame accounted for: on serial by sequence number (no gap, no
    duplicate), on both links by count (one pair every ``telem_div`` ticks).
metrics
    per chunk (a whole number of reference periods): RMS and peak tilt, RMS tracking error,
    peak duty; every chunk after the first must match the first within a tolerance, and
    the board must be balancing, fault-free, throughout.

It prints a summary table per chunk and a verdict; the exit status is 0 only if every
check passed.  :func:`soak` returns the same as a :class:`SoakResult` (the short soak in
``make test`` calls it directly).

The run is THE lockstep loop (:class:`host.hil.lockstep.Lockstep`, strict and pipelined);
the chunks are its ``after_tick`` hook.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from firmware import msgtable as T
from host.hil.accounting import Sink
from host.hil.errors import HilError
from host.hil.lockstep import Lockstep
from host.hil.session import HilSession
from host.link import messages as M
from sim.params import RobotParams, load_params
from sim.plantsim import PlantSim
from sim.scenario import load_scenario, scenario_from_dict

__all__ = ["PERIOD_S", "SoakResult", "soak"]

PERIOD_S = 4.4  # the square wave's period: chunks are whole periods
_BALANCING = 2


@dataclass
class SoakResult:
    """Outcome of :func:`soak`.

    Attributes
    ----------
    chunks : list of dict
        Per chunk: ``t0``, ``t1`` (s), ``rms_phi`` (rad), ``peak_phi`` (rad),
        ``rms_err`` (m, x - x_ref), ``peak_duty``, ``step_us_mean``, ``step_us_median``,
        ``step_us_max`` (from telemetry), ``telemetry`` (pairs received), ``ticks_per_s`` (host wall rate),
        ``not_balancing`` (ticks answered in another state).
    stats : dict
        Whole-run figures: ticks, telemetry accounting, firmware probe, uptime.
    failures : list of str
        Every check that failed (empty: passed).
    """

    chunks: list[dict[str, float]] = field(default_factory=list)
    stats: dict[str, Any] = field(default_factory=dict)
    failures: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True if every check passed."""
        return not self.failures

    def table(self) -> str:
        """The per-chunk summary as fixed-width text."""
        head = (f"{'chunk':>5} {'t0 s':>7} {'t1 s':>7} {'phi rms':>9} {'|phi|max':>9} {'err rms':>8} "
                f"{'|duty|max':>9} {'step us':>8} {'max us':>7} {'telem':>6} {'tick/s':>7}")
        rows = [head, "-" * len(head)]
        for i, c in enumerate(self.chunks):
            rows.append(f"{i:>5} {c['t0']:>7.1f} {c['t1']:>7.1f} {c['rms_phi']:>9.2e} {c['peak_phi']:>9.2e} "
                        f"{c['rms_err']:>8.4f} {c['peak_duty']:>9.0f} {c['step_us_mean']:>8.1f} "
                        f"{c['step_us_max']:>7.0f} {c['telemetry']:>6.0f} {c['ticks_per_s']:>7.0f}")
        return "\n".join(rows)


def _scenario(seconds: float) -> Any:
    base = load_scenario("square_wave_20cm_2p2s")
    ref = base.reference
    return scenario_from_dict({
        "name": "soak", "description": f"{seconds:g} s of the square-wave reference", "duration": float(seconds),
        "seed": base.seed,
        "reference": {"kind": "square", "start": ref.start, "amplitude": ref.amplitude, "period": ref.period},
    })


def soak(sim_seconds: float, *, link: str = "serial", chunk_s: float | None = None, params: RobotParams | None = None,
         tolerance: float = 0.1, progress: Callable[[float, float], None] | None = None,
         timeout: float = 2.0, result: SoakResult | None = None) -> SoakResult:
    """Run the soak (see the module docstring).

    Parameters
    ----------
    sim_seconds : float
        Simulated time (s), at least two reference periods (8.8 s).
    link : {"serial", "can"}
        Framing.
    chunk_s : float, optional
        Chunk length (s), rounded to whole reference periods; default about a tenth of
        the run (at least one period).
    params : RobotParams, optional
        Robot parameters (default ``sim/robot.toml``).
    tolerance : float
        Largest relative difference of a chunk's RMS tilt / tracking error / peak duty from
        the first chunk's.
    progress : callable, optional
        ``progress(sim_time_done, sim_seconds)`` once per chunk.
    timeout : float
        Seconds to wait for an answer.
    result : SoakResult, optional
        Filled in as the run goes (a chunk's row as soon as it is finished) and returned, so
        a caller interrupted mid-run still holds the finished chunks.

    Returns
    -------
    SoakResult
    """
    if not sim_seconds >= 2 * PERIOD_S:
        raise ValueError(f"sim_seconds must be at least {2 * PERIOD_S:g} (two reference periods), got {sim_seconds!r}")
    if link not in ("serial", "can"):
        raise ValueError(f"link must be 'serial' or 'can', got {link!r}")
    if not 0 < tolerance < 1:
        raise ValueError(f"tolerance must be in (0, 1), got {tolerance!r}")
    params = params or load_params()
    periods = max(1, round((chunk_s if chunk_s else sim_seconds / 10) / PERIOD_S))
    chunk_s = periods * PERIOD_S
    res = SoakResult() if result is None else result
    scen = _scenario(sim_seconds)
    sess = HilSession(link=link, timeout=timeout, probe=True)
    sess.open()
    try:
        _run(sess, scen, params, chunk_s, res, progress)
    finally:
        sess.close()
    try:
        probe = sess.probe()
    except HilError as exc:
        res.failures.append(f"firmware: {exc}")
        probe = {}
    res.stats["probe"] = probe
    _check(res, probe, tolerance)
    return res


def _run(sess: HilSession, scen: Any, params: RobotParams, chunk_s: float, res: SoakResult,
         progress: Callable[[float, float], None] | None) -> None:
    link = sess._link()
    sim = PlantSim(params, scen)
    sess.prepare(sim)
    sink = Sink(link)
    hb0 = link.query("heartbeat", timeout=sess.timeout / 4, retries=3)
    telem_div = link.param_get(T.P_TELEM_DIV)
    chunks = _Chunks(sim, sink, int(round(chunk_s * sim.params.rate)), res, progress)
    # THE lockstep loop, strict and pipelined, without per-tick records (an hour is 1.8 M
    # ticks): the chunks keep what they need
    loop = Lockstep(sess, sim, sink=sink, depth=sim.sensor_model.delay_steps, after_tick=chunks.tick,
                    record=False).run()
    # let the last periodic frames arrive, then read the clock again
    loop.drain(0.1)
    hb1 = link.query("heartbeat", timeout=sess.timeout / 4, retries=3)
    n = loop.n
    res.stats.update({
        "ticks": n, "link": sess.link_kind, "telem_div": telem_div, "telemetry": sink.telemetry,
        "faults_seen": chunks.faults_seen, "uptime0_ms": hb0.uptime_ms, "uptime1_ms": hb1.uptime_ms,
        "state_end": hb1.state, "period_ms": 1000.0 / sim.params.rate,
    })
    if sess.link_kind == "serial":
        res.stats.update(sink.acct.stats())
    res.stats["host_drops"] = dict(link.drops)
    res.stats["nacks"] = list(sink.nacks)
    sess.finish()


class _Chunks:
    # the loop's after_tick hook: per-tick states and faults, a row of metrics per chunk
    def __init__(self, sim: PlantSim, sink: Sink, per_chunk: int, res: SoakResult,
                 progress: Callable[[float, float], None] | None) -> None:
        self.sim, self.sink, self.per_chunk, self.res, self.progress = sim, sink, per_chunk, res, progress
        self.states = np.zeros(per_chunk, dtype=np.int64)
        self.faults_seen = 0
        self.start = 0
        self.wall = time.perf_counter()
        self.tel = 0
        self.step0 = 0

    def tick(self, k: int, m: Any) -> None:
        self.states[k - self.start] = m.state
        self.faults_seen |= m.faults
        n = self.sim.n_ticks
        if k + 1 - self.start != self.per_chunk and k + 1 != n:
            return
        sim, sink, Ts = self.sim, self.sink, self.sim.Ts
        log = sim.result()
        cnt = k + 1 - self.start
        st = np.asarray(sink.step_us[self.step0:], dtype=float)
        err = log["x"] - log["x_ref"]
        now = time.perf_counter()
        self.res.chunks.append({
            "t0": self.start * Ts, "t1": (k + 1) * Ts,
            "rms_phi": float(np.sqrt(np.mean(log["phi"] ** 2))), "peak_phi": float(np.max(np.abs(log["phi"]))),
            "rms_err": float(np.sqrt(np.mean(err ** 2))), "peak_duty": float(np.max(np.abs(log["duty"]))),
            "step_us_mean": float(st.mean()) if st.size else math.nan,
            "step_us_median": float(np.median(st)) if st.size else math.nan,
            "step_us_max": float(st.max()) if st.size else math.nan,
            "telemetry": float(sink.telemetry - self.tel), "ticks_per_s": cnt / max(now - self.wall, 1e-9),
            "not_balancing": float(np.count_nonzero(self.states[:cnt] != _BALANCING)),
        })
        # keep memory flat over an hour: the plant's log and the step times restart with each chunk
        for v in sim._log.values():
            v.clear()
        sink.step_us.clear()
        self.start, self.wall, self.tel, self.step0 = k + 1, now, sink.telemetry, 0
        if self.progress is not None:
            self.progress((k + 1) * Ts, n * Ts)


def _check(res: SoakResult, probe: dict[str, int], tol: float) -> None:
    s, f = res.stats, res.failures
    if probe:
        if probe.get("locked") != 1:
            f.append("heap: the firmware did not run under heap_lock")
        if probe.get("alloc0") != probe.get("alloc1"):
            f.append(f"heap: gc.mem_alloc() {probe.get('alloc0')} at the start, {probe.get('alloc1')} at the end")
        drops = sum(v for k, v in probe.items() if k in ("n_crc", "n_length", "n_unknown", "n_overrun", "n_framing"))
        if drops:
            f.append(f"firmware decoder dropped {drops} frame(s) on a clean link: {probe}")
    if not s:
        return
    # the board's clock: exactly one period per tick between the two heartbeats
    ticks = s["ticks"]
    want = ticks * s["period_ms"]
    # heartbeat.uptime_ms wraps at its field width (msgtable): compare modulo that
    wrap = 1 << (8 * next(f.size for f in M.BY_NAME["heartbeat"].FIELDS if f.name == "uptime_ms"))
    err = ((s["uptime1_ms"] - s["uptime0_ms"]) - want + wrap // 2) % wrap - wrap // 2
    got = want + err  # the advance nearest the expected one
    s["uptime_advance_ms"] = got
    if abs(err) > s["period_ms"]:
        f.append(f"timing drift: the board's uptime advanced {got} ms over {ticks} ticks (expected {want:g})")
    if s["faults_seen"] or s["state_end"] != _BALANCING:
        f.append(f"board left balancing: faults 0x{s['faults_seen']:x}, final state {s['state_end']}")
    # telemetry: one pair every telem_div ticks, and (serial) no sequence gap
    div = s["telem_div"]
    if div > 0:
        expect = ticks / div
        if abs(s["telemetry"] - expect) > 2:
            f.append(f"telemetry: {s['telemetry']} pairs received, {expect:g} expected")
    if s.get("seq_lost") or s.get("duplicates") or s.get("half_pairs"):
        f.append(f"telemetry sequence: {s['seq_lost']} lost, {s['duplicates']} duplicated, "
                 f"{s['half_pairs']} half pairs")
    if s.get("nacks"):
        f.append(f"the firmware refused {len(s['nacks'])} frame(s) on a clean link: {s['nacks'][0]}")
    if sum(s.get("host_drops", {}).values()):
        f.append(f"host decoder dropped frames on a clean link: {s['host_drops']}")
    # metrics stable: every full chunk like the first
    full = [c for c in res.chunks if abs((c["t1"] - c["t0"]) - (res.chunks[0]["t1"] - res.chunks[0]["t0"])) < 1e-6]
    ref = full[0]
    for i, c in enumerate(full[1:], 1):
        for key, floor in (("rms_phi", 1e-4), ("rms_err", 1e-3), ("peak_duty", 50.0)):
            if abs(c[key] - ref[key]) > tol * ref[key] + floor:
                f.append(f"chunk {i}: {key} {c[key]:.4g} vs {ref[key]:.4g} in the first chunk")
        # the median: a step the OS preempted (another process on the machine) is not drift
        if c["step_us_median"] > 2.0 * ref["step_us_median"] + 10:
            f.append(f"chunk {i}: firmware step (median) {c['step_us_median']:.1f} us, first chunk "
                     f"{ref['step_us_median']:.1f} us")
    for i, c in enumerate(res.chunks):
        if c["not_balancing"]:
            f.append(f"chunk {i}: {c['not_balancing']:.0f} ticks not balancing")
