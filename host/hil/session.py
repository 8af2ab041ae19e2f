"""Hardware-in-the-loop runner: the firmware closes the loop with the simulated plant.

A :class:`HilSession` owns one connection to a board running the firmware's HIL main
(:mod:`firmware.main_hil`): a real board on a serial port or CAN channel, or the virtual
board -- the MicroPython unix port on a pty (:mod:`host.boards.vport`).  Per scenario it runs the
plant of :class:`sim.plantsim.PlantSim` against the firmware, tick by tick:

lockstep (deterministic; :meth:`HilSession.run_lockstep`)
    For tick k the host sends the ``hil_sensor`` frame (tick k, ADC counts, encoder
    counter), the firmware runs exactly one ``app.step()`` and answers ``hil_actuator``
    (tick k, duty, state, faults); the plant integrates that duty for one period.  Every
    answer must carry the tick just sent -- a lost or repeated tick raises
    :class:`TickError`.  The run is bit-identical across runs and links.

    Pipelining: the reading the board gets at tick k+j (j <= the measurement delay in
    ticks, 5 at 10 ms / 500 Hz) was taken at tick k+j-delay <= k, so it is already known
    while the board works on tick k.  The host therefore keeps up to ``pipeline`` sensor
    frames in flight (default: the delay), which lets the host's plant and the firmware
    run on two cores at once.  The firmware still handles one frame after the other, so
    this changes nothing in what it computes.

real time (:meth:`HilSession.run_realtime`)
    The firmware paces its own loop at the loop rate with ``ticks_us``; the host streams
    one sensor frame per period on its own clock, phase-locked so that frames arrive about
    half a period before the firmware's tick, and steps the plant with the duty received
    for that tick (or the previous one if it is late, counted as ``late``).  The host
    measures the sensor-to-actuator latency of every tick and the jitter of the answers'
    spacing, and reads the firmware's own ``timing`` statistics (step time, longest period,
    overruns) at the end.

Before each scenario the board is disarmed, its faults cleared, the arm threshold opened
(``arm_tilt_mrad`` = its maximum, so a large initial tilt is caught), the reference set,
one priming sensor frame with the initial reading sent (tick :data:`PRIME_TICK`), then
armed; the reference follows the scenario with ``set_reference`` frames placed in the
stream just before the tick they apply to.

:func:`run_scenarios` runs a list of scenarios and writes, per scenario, the CSV log, a PNG
of the signals (with the float pure simulation overlaid when ``compare=True``) and a GIF;
it returns the :class:`HilRun` records whose summaries :func:`sim.metrics.summary_table`
prints.

A fault-injection hook (``fault=``, see :class:`FaultyPort`) sits in the host-side link
path: it can corrupt, drop or duplicate bytes in either direction without touching the
firmware or the protocol code.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from firmware import msgtable as T
from host.link import messages as M
from host.link.clients import CanLink, CommandRefused, Link, LinkError, SerialLink
from host.boards.vport import PTMX, BoardExited, PortError, VirtualBoard, open_can, set_realtime, slave_of, steal_seconds
from sim.params import RobotParams, load_params
from sim.plantsim import PlantSim, write_csv
from sim.scenario import REPORT_SCENARIOS, Scenario, list_scenarios, load_scenario

__all__ = [
    "HilError",
    "TickError",
    "FaultyPort",
    "HilRun",
    "HilSession",
    "PRIME_TICK",
    "encoder_jump_limit",
    "design_noise",
    "float_reference",
    "resolve_scenarios",
    "run_scenarios",
    "write_outputs",
]

PRIME_TICK = (1 << 30) - 1
"""Tick number of the priming sensor frame sent before each scenario."""

LINKS = ("serial", "can")
_CAN_PTY_TIMEOUT = 0.0005
MODES = ("lockstep", "realtime")

_SENSOR = M.BY_NAME["hil_sensor"]
_ACTUATOR = M.BY_NAME["hil_actuator"]
_SET_REF = M.BY_NAME["set_reference"]
_TELEM_STATE = M.BY_NAME["telem_state"]
_TELEM_CTRL = M.BY_NAME["telem_ctrl"]
_HEARTBEAT = M.BY_NAME["heartbeat"]
_TIMING = M.BY_NAME["timing"]
_NACK = M.BY_NAME["nack"]
_ACK = M.BY_NAME["ack"]
_ARM_TILT_MAX = next(p[4] for p in T.PARAMS if p[0] == T.P_ARM_TILT)
_STATE_NAMES = {s[0]: s[1] for s in T.STATES}


class HilError(RuntimeError):
    """The HIL loop could not run or went wrong (the message says where)."""


class TickError(HilError):
    """The firmware's answer did not carry the tick just sent (a tick lost or repeated)."""


# ---------------------------------------------------------------- fault injection
class FaultyPort:
    """A pyserial-like wrapper that passes every byte through fault hooks.

    Parameters
    ----------
    inner : serial.Serial-like
        The real port (pyserial object of a :class:`~host.link.clients.SerialLink`, or of
        python-can's ``serial`` interface bus).
    tx : callable, optional
        ``tx(data: bytes) -> bytes`` applied to everything the host writes (corrupt, drop,
        duplicate...).
    rx : callable, optional
        ``rx(data: bytes) -> bytes`` applied to everything the host reads.

    Notes
    -----
    Attribute access not defined here goes to ``inner`` (``timeout``, ``in_waiting``,
    ``fileno``, ``close``...).  ``rx`` is applied per read call, so a hook that drops bytes
    can make a fixed-size read return short, exactly like a lossy line.
    """

    def __init__(self, inner: Any, *, tx: Callable[[bytes], bytes] | None = None,
                 rx: Callable[[bytes], bytes] | None = None) -> None:
        object.__setattr__(self, "_inner", inner)
        object.__setattr__(self, "_tx", tx)
        object.__setattr__(self, "_rx", rx)

    def write(self, data: bytes) -> int:
        out = bytes(data) if self._tx is None else self._tx(bytes(data))
        if out:
            self._inner.write(out)
        return len(data)

    def read(self, size: int = 1) -> bytes:
        data = self._inner.read(size)
        return data if self._rx is None or not data else self._rx(data)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._inner, name, value)


def _install_fault(link: Link, tx: Callable[[bytes], bytes] | None, rx: Callable[[bytes], bytes] | None) -> None:
    # SerialLink keeps its pyserial port in ._ser; python-can's serial bus in .bus._ser
    holder = link.bus if isinstance(link, CanLink) else link
    inner = getattr(holder, "_ser", None)
    if inner is None:
        raise HilError(f"fault injection needs a byte-stream link, not {type(holder).__name__}")
    holder._ser = FaultyPort(inner, tx=tx, rx=rx)


# ---------------------------------------------------------------- results
@dataclass
class HilRun:
    """One scenario closed through the firmware.

    Attributes
    ----------
    scenario : Scenario
        What was run.
    params : RobotParams
        Plant parameters actually simulated (the scenario's overrides applied).
    log : dict of ndarray
        The run log (:data:`sim.plantsim.LOG_COLUMNS`) plus ``fw_state``, ``fw_faults``
        per tick and, in real time, ``latency_us`` and ``late``.
    mode, link : str
        How it was run.
    wall_s : float
        Wall-clock duration of the closed loop (set-up excluded).
    stats : dict
        Counts and timing: ``ticks``, ``telemetry`` frames, ``telemetry_lost`` (periodic
        frames -- telemetry and heartbeats, one counter on the board -- missing by serial
        sequence number between the first and the last received, half telemetry pairs
        included; ``None`` over CAN, whose frames carry no sequence number), ``fw_step_us_mean/max`` (from telemetry), time split
        ``plant_s``/``link_s``; in real time also latency and jitter figures and the
        firmware's ``timing`` message (``fw_*``).
    reference : dict of ndarray, optional
        The float pure-simulation log of the same scenario, when compared.
    """

    scenario: Scenario
    params: RobotParams
    log: dict[str, np.ndarray]
    mode: str
    link: str
    wall_s: float
    stats: dict[str, Any] = field(default_factory=dict)
    reference: dict[str, np.ndarray] | None = None

    @property
    def name(self) -> str:
        """Scenario name."""
        return self.scenario.name

    @property
    def realtime_factor(self) -> float:
        """Simulated seconds per wall-clock second."""
        return self.scenario.duration / self.wall_s if self.wall_s > 0 else math.inf

    def phi_error(self) -> float:
        """Largest ``|phi_hil - phi_float|`` (rad) against the float reference (nan if none).

        Compared while the firmware controls the motor: once its supervisor has cut the
        motor (a fault), the float design -- which has no supervisor -- runs on alone.
        """
        if self.reference is None:
            return math.nan
        n = min(len(self.log["phi"]), len(self.reference["phi"]))
        state = self.log.get("fw_state")
        if state is not None:
            cut = np.nonzero(np.asarray(state[:n]) == _FAULT_STATE)[0]
            n = int(cut[0]) if cut.size else n
        return float(np.max(np.abs(self.log["phi"][:n] - self.reference["phi"][:n]))) if n else 0.0

    def summary(self, name: str | None = None) -> Any:
        """Metrics and constraint checks (:class:`sim.metrics.RunSummary`)."""
        from sim.metrics import evaluate

        return evaluate(self.log, self.scenario, self.params, name=name or self.name)


# ---------------------------------------------------------------- the session
class HilSession:
    """A connection to a board running the firmware's HIL main, real or virtual.

    Parameters
    ----------
    port : str, optional
        Serial device (``/dev/ttyACM0``) or, with ``link="can"``, the python-can channel;
        ``None`` (default) starts the virtual board on a pty.
    link : {"serial", "can"}
        Framing: COBS serial frames, or CAN frames (python-can ``serial``-interface bytes
        over the pty in the virtual case).
    mode : {"lockstep", "realtime"}
        Loop mode the firmware runs (a real board must have been started in that mode).
    node : int
        CAN node id of the board.
    can_interface : str
        python-can interface for a real CAN channel (``socketcan``, ``slcan``, ...).
    baudrate : int
        Serial line rate for a real port.
    timeout : float
        Seconds to wait for any one answer of the firmware.
    fault_tx, fault_rx : callable, optional
        Fault-injection hooks on the host's byte stream (see :class:`FaultyPort`).
    heapsize : str, optional
        MicroPython heap of the virtual board.
    rt_priority : int or None
        Real time only: ``SCHED_FIFO`` priority of the virtual board's interpreter and of
        the host's streaming loop during a run (see :func:`host.boards.vport.set_realtime`);
        ``None`` leaves both to the normal scheduler.
    heap_lock : bool
        Virtual board: run the firmware loop under ``micropython.heap_lock()`` (any
        allocation ends the run, reported as :class:`~host.boards.vport.BoardExited`).

    Raises
    ------
    ValueError
        Unknown link or mode.
    """

    def __init__(self, port: str | None = None, *, link: str = "serial", mode: str = "lockstep", node: int = 1,
                 can_interface: str = "serial", baudrate: int = 115200, timeout: float = 2.0,
                 fault_tx: Callable[[bytes], bytes] | None = None, fault_rx: Callable[[bytes], bytes] | None = None,
                 heapsize: str | None = None, rt_priority: int | None = 20, heap_lock: bool = False) -> None:
        if link not in LINKS:
            raise ValueError(f"link must be one of {', '.join(LINKS)}, got {link!r}")
        if mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
        if not 0 <= int(node) < 2**T.NODE_BITS:
            raise ValueError(f"node must be in 0..{2**T.NODE_BITS - 1}, got {node!r}")
        if not timeout > 0:
            raise ValueError(f"timeout must be > 0, got {timeout!r}")
        self.port = port
        self.link_kind = link
        self.mode = mode
        self.node = int(node)
        self.can_interface = can_interface
        self.baudrate = int(baudrate)
        self.timeout = float(timeout)
        self.heapsize = heapsize
        self.rt_priority = rt_priority
        self.heap_lock = bool(heap_lock)
        self._fault = (fault_tx, fault_rx)
        self.link: Link | None = None
        self.board: VirtualBoard | None = None
        self._bus: Any = None
        self._table_key: Any = (None, None)
        self._gains_label = "firmware default"
        self.gains = self._gains_label
        self._custom: tuple[bytes, str] | None = None

    @property
    def virtual(self) -> bool:
        """True for the MicroPython unix port on a pty."""
        return self.port is None

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> "HilSession":
        """Open the link (and start the virtual board).

        Raises
        ------
        PortError
            Bad port or CAN channel (one-line message).
        BoardExited
            The virtual firmware failed to start.
        """
        try:
            if self.link_kind == "can":
                if self.virtual:
                    # python-can's serial interface ignores recv()'s timeout and waits the
                    # port's own: keep it short, or every idle recv() costs 0.1 s
                    self._bus = open_can(PTMX, interface="serial", timeout=_CAN_PTY_TIMEOUT)
                else:
                    self._bus = open_can(self.port, interface=self.can_interface)
                self.link = CanLink(self._bus, node_id=self.node)
                fd = self._bus.fileno() if self.virtual else -1
            else:
                url = PTMX if self.virtual else str(self.port)
                try:
                    self.link = SerialLink(url, baudrate=self.baudrate)
                except LinkError as exc:
                    raise PortError(f"cannot open serial port {url!r}: {_cause(exc)}") from exc
                fd = self.link._ser.fileno() if self.virtual else -1
            if self.virtual:
                slave = slave_of(fd)
                self.board = VirtualBoard(slave, link=self.link_kind, mode=self.mode, node=self.node,
                                          heapsize=self.heapsize, heap_lock=self.heap_lock,
                                          rt_priority=self.rt_priority if self.mode == "realtime" else None,
                                          code=self._board_code(slave))
                self.board.start()
            if any(self._fault):
                _install_fault(self.link, *self._fault)
        except BaseException:
            self.close()
            raise
        return self

    def _board_code(self, slave: str) -> str | None:
        """MicroPython source the virtual board runs on ``slave`` (``None``: the standard HIL main).

        Subclasses override it to wrap the unchanged firmware (e.g. a probe of its heap).
        """
        return None

    def close(self) -> None:
        """Close the link and stop the virtual board (idempotent)."""
        if self.link is not None:
            try:
                self.link.close()
            except (LinkError, OSError):
                pass
            self.link = None
        if self._bus is not None:
            try:
                self._bus.shutdown()
            except Exception:  # noqa: BLE001 - best effort at shutdown
                pass
            self._bus = None
        if self.board is not None:
            self.board.stop()

    def __enter__(self) -> "HilSession":
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ helpers
    def _link(self) -> Link:
        if self.link is None:
            raise HilError("session is not open")
        return self.link

    def _check_board(self) -> None:
        if self.board is not None:
            self.board.check()

    def _recv(self, timeout: float) -> Any:
        link = self._link()
        try:
            return link.recv(timeout)
        except LinkError as exc:
            self._check_board()
            raise HilError(f"link failed: {exc}") from exc

    def _request(self, fn: Callable[..., Any], *args: Any) -> Any:
        try:
            return fn(*args, timeout=self.timeout / 4, retries=3)
        except CommandRefused:
            raise
        except LinkError as exc:
            self._check_board()
            raise HilError(f"{getattr(fn, '__name__', 'request')}: {exc}") from exc

    def _sensor(self, tick: int, adc: int, enc: int) -> int:
        return self._link().send(_SENSOR(tick=tick & PRIME_TICK, adc=int(adc), enc=int(enc)))

    def _set_ref(self, x: float) -> None:
        self._link().send(_SET_REF(x_um=int(round(x * 1e6))))

    def _await_actuator(self, tick: int, sink: "_Sink") -> Any:
        # next hil_actuator; other messages go to the sink
        deadline = time.monotonic() + self.timeout
        while True:
            m = self._recv(max(0.0, deadline - time.monotonic()))
            if m is None:
                self._check_board()
                raise HilError(f"no answer from the firmware for tick {tick} within {self.timeout:g} s")
            if isinstance(m, _ACTUATOR):
                return m
            sink.other(m)

    def use_gains(self, blob: bytes | None, label: str = "custom table") -> None:
        """Run the following scenarios with this gain table instead of the design's.

        ``blob`` is an exported table (``host.design.export.export(...).blob()``); it is uploaded
        by the next :meth:`prepare` and stays until ``use_gains(None)`` gives the design's
        tables (with the scenario's noise adjustments) back.
        """
        self._custom = None if blob is None else (bytes(blob), str(label))

    def _ensure_gains(self, encj: int | None, sigma: tuple[float, float] | None = None) -> str:
        # upload the design's table with the encoder plausibility limit widened to
        # `encj` counts per tick and the estimator designed for measurement noise `sigma`
        # (None, None: the firmware's own table), or the table set by use_gains();
        # returns a label
        key: Any = ("custom", self._custom) if self._custom is not None else (encj, sigma)
        if key == self._table_key:
            return self._gains_label
        blob, label = self._custom if self._custom is not None else _gain_table(encj, sigma)
        try:
            self._link().upload_gains(blob, timeout=self.timeout / 4, retries=3)
        except LinkError as exc:
            self._check_board()
            raise HilError(f"gain table upload ({label}) failed: {exc}") from exc
        self._table_key = key
        self._gains_label = label
        return label

    def prepare(self, sim: PlantSim, sink: "_Sink | None" = None, *, arm: bool = True,
                fw_params: Mapping[str | int, int] | None = None) -> None:
        """Bring the board to a clean start for a run (see the module docstring).

        If the scenario puts measurement noise on the sensors, the design's gain table is
        uploaded with the estimator designed for that noise
        (:func:`host.design.discrete.sigma_meas_for`) and, where the firmware's encoder
        plausibility check (largest step per tick) would take the noise for lost counts,
        that limit widened (:func:`encoder_jump_limit`); the next scenario without noise
        gets the firmware's own table back.  ``fw_params`` sets firmware parameters (name or index ->
        value, see ``firmware.msgtable.PARAMS``) before arming; they stay set for the
        session.
        """
        link = self._link()
        sink = sink or _Sink()
        self._request(link.disarm)
        adc, enc = sim.read()
        if self.mode == "lockstep":
            # the initial reading, before the faults are cleared: the jump from the last
            # run's final reading must not count against this one
            self._sensor(PRIME_TICK, adc, enc)
            a = self._await_actuator(PRIME_TICK, sink)
            if a.tick != PRIME_TICK:
                raise TickError(f"priming frame answered with tick {a.tick}")
        self._request(link.clear_faults)
        self.gains = self._ensure_gains(encoder_jump_limit(sim.scenario, sim.params), design_noise(sim.scenario, sim.params))
        self._request(link.param_set, T.P_ARM_TILT, _ARM_TILT_MAX)
        for key, value in (fw_params or {}).items():
            self._request(link.param_set, key, int(value))
        self._request(link.set_reference, sim.x_ref())
        if arm:
            self._request(link.arm)
        _drain(link, sink, -1)

    def finish(self) -> dict[str, int]:
        """Disarm after a run and read the firmware's timing statistics."""
        link = self._link()
        self._request(link.disarm)
        try:
            t = self._request(link.query, "timing")
        except (CommandRefused, HilError):
            return {}
        return {f"fw_{k}": int(v) for k, v in zip((f.name for f in t.FIELDS), t.values())}

    # ------------------------------------------------------------------ lockstep
    def run_lockstep(self, scenario: Scenario, params: RobotParams | None = None, *, pipeline: int | None = None,
                     progress: Callable[[int, int], None] | None = None, seed: int | None = None,
                     x0: Sequence[float] | None = None, fw_params: Mapping[str | int, int] | None = None) -> HilRun:
        """Run one scenario in lockstep (deterministic; see the module docstring).

        Parameters
        ----------
        scenario : Scenario
            The scenario.
        params : RobotParams, optional
            Robot parameters (default: ``sim/robot.toml``).
        pipeline : int, optional
            Sensor frames kept in flight, at most the measurement delay in ticks (default:
            that delay); 0 = strictly one frame at a time.
        progress : callable, optional
            ``progress(tick, n_ticks)``, called every 250 ticks.
        seed : int, optional
            Noise seed overriding the scenario's.
        x0 : sequence of 4 float, optional
            Initial state overriding the scenario's.
        fw_params : mapping, optional
            Firmware parameters to set first (see :meth:`prepare`).

        Raises
        ------
        TickError
            A tick was lost or repeated.
        HilError
            The firmware stopped answering or the link failed.
        """
        if self.mode != "lockstep":
            raise HilError("this session's firmware runs in real-time mode; use run_realtime")
        params = params or load_params()
        sim = PlantSim(params, scenario, seed=seed, x0=x0)
        sink = _Sink(self._link())
        self.prepare(sim, sink, fw_params=fw_params)
        d = sim.sensor_model.delay_steps
        depth = d if pipeline is None else max(0, min(int(pipeline), d))
        n = sim.n_ticks
        link = self._link()
        fw_state = np.zeros(n, dtype=np.int64)
        fw_faults = np.zeros(n, dtype=np.int64)
        send = link.send
        recv = link.recv
        timeout = self.timeout
        ref_prev = sim.x_ref()
        Ts = sim.Ts
        x_ref_at = scenario.x_ref
        t_plant = 0.0
        t_link = 0.0
        t0 = time.perf_counter()
        sent = 0
        for k in range(n):
            # keep `depth` frames ahead of the board (readings already determined)
            c0 = time.perf_counter()
            while sent < n and sent - k <= depth:
                j = sent - k
                p0 = time.perf_counter()
                adc, enc = sim.read() if j == 0 else _peek(sim, j)
                ref = float(x_ref_at(sent * Ts))
                t_plant += time.perf_counter() - p0
                if ref != ref_prev:
                    send(_SET_REF(x_um=int(round(ref * 1e6))))
                    ref_prev = ref
                send(_SENSOR(tick=sent, adc=int(adc), enc=int(enc)))
                sent += 1
            c1 = time.perf_counter()
            deadline = c1 + timeout
            while True:
                try:
                    # heartbeats keep coming while the firmware waits: bound the whole wait
                    m = recv(max(0.0, deadline - time.perf_counter()))
                except LinkError as exc:
                    self._check_board()
                    raise HilError(f"link failed at tick {k}: {exc}") from exc
                if m is None:
                    self._check_board()
                    raise HilError(f"no answer from the firmware for tick {k} within {timeout:g} s")
                if type(m) is _ACTUATOR:
                    break
                sink.other(m, k)
            c2 = time.perf_counter()
            if m.tick != k:
                what = "repeated" if m.tick < k else "lost"
                raise TickError(f"tick {k}: the firmware answered tick {m.tick} (tick {min(k, m.tick)} {what})")
            fw_state[k] = m.state
            fw_faults[k] = m.faults
            sim.step(m.duty)
            c3 = time.perf_counter()
            t_plant += c3 - c2
            t_link += c2 - c0
            if progress is not None and k % 250 == 0:
                progress(k, n)
        wall = time.perf_counter() - t0
        if progress is not None:
            progress(n, n)
        stats = self.finish()
        _drain(link, sink, n)
        log = sim.result()
        log["fw_state"] = fw_state
        log["fw_faults"] = fw_faults
        stats.update(sink.stats())
        stats.update({"ticks": n, "gains": self.gains, "pipeline": depth, "plant_s": t_plant, "link_s": t_link, "wall_s": wall})
        return HilRun(scenario, sim.params, log, "lockstep", self.link_kind, wall, stats)

    # ------------------------------------------------------------------ real time
    def run_realtime(self, scenario: Scenario, params: RobotParams | None = None, *, lead: float = 0.5,
                     sync_ticks: int = 100, progress: Callable[[int, int], None] | None = None,
                     seed: int | None = None, x0: Sequence[float] | None = None,
                     fw_params: Mapping[str | int, int] | None = None) -> HilRun:
        """Run one scenario in real time (the firmware paces itself; see the module docstring).

        Parameters
        ----------
        scenario : Scenario
            The scenario.
        params : RobotParams, optional
            Robot parameters (default: ``sim/robot.toml``).
        lead : float
            Fraction of a period by which a sensor frame should precede the firmware's tick
            (the host phase-locks its stream to the answers).
        sync_ticks : int
            Periods streamed before the scenario (board disarmed, initial reading) to lock
            the phase.
        progress, seed, x0, fw_params
            As for :meth:`run_lockstep`.

        The run's ``stats`` hold the host's measurements (``latency_us_*``, ``late``,
        ``answered``), the firmware's own timing statistics (``fw_*``) and ``steal_s``: the
        CPU time the hypervisor took from the machine during the run
        (:func:`host.boards.vport.steal_seconds`), against which the timing figures are read.
        """
        if self.mode != "realtime":
            raise HilError("this session's firmware runs in lockstep mode; use run_lockstep")
        if not 0.05 <= lead <= 0.9:
            raise ValueError(f"lead must be in [0.05, 0.9] of a period, got {lead!r}")
        params = params or load_params()
        sim = PlantSim(params, scenario, seed=seed, x0=x0)
        sink = _Sink(self._link())
        link = self._link()
        # armed later, in the stream, once the phase is locked on the initial reading
        self.prepare(sim, sink, arm=False, fw_params=fw_params)
        n = sim.n_ticks
        T_s = sim.Ts
        clock = time.perf_counter
        adc0, enc0 = sim.read()
        fw_state = np.zeros(n, dtype=np.int64)
        fw_faults = np.zeros(n, dtype=np.int64)
        latency = np.full(n, np.nan)
        late = np.zeros(n, dtype=np.int64)
        send_t: dict[int, float] = {}
        pll = _PhaseLock(T_s, lead)
        state = {"duty": 0}
        x_ref_at = scenario.x_ref

        def pump(until: float, want: int | None) -> Any:
            # receive until `until` (or the answer for tick `want`); returns that answer
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
                        pll.observe(now - ts)
                        if 0 <= m.tick < n:
                            latency[m.tick] = (now - ts) * 1e6
                    if want is not None and m.tick == want:
                        got = m
                        if until - clock() > 0:
                            return got
                else:
                    sink.other(m, want if want is not None else -1)

        host_rt = set_realtime(self.rt_priority - 1) if self.rt_priority and self.rt_priority > 1 else False
        try:
            return self._realtime_loop(sim, sink, link, n, T_s, clock, adc0, enc0, fw_state, fw_faults, latency,
                                       late, send_t, pll, state, x_ref_at, pump, sync_ticks, progress, scenario,
                                       host_rt)
        finally:
            if host_rt:
                set_realtime(None)

    def _realtime_loop(self, sim: PlantSim, sink: "_Sink", link: Link, n: int, T_s: float, clock: Any, adc0: int,
                       enc0: int, fw_state: np.ndarray, fw_faults: np.ndarray, latency: np.ndarray,
                       late: np.ndarray, send_t: dict[int, float], pll: "_PhaseLock", state: dict[str, int],
                       x_ref_at: Any, pump: Any, sync_ticks: int, progress: Any, scenario: Scenario,
                       host_rt: bool) -> HilRun:
        t_next = clock() + 0.01
        # phase lock on the resting initial reading (disarmed, duty 0)
        for i in range(sync_ticks):
            _sleep_until(t_next)
            tick = (PRIME_TICK - sync_ticks + i) & PRIME_TICK
            send_t[tick] = clock()
            self._sensor(tick, adc0, enc0)
            pump(t_next + T_s * 0.9, None)
            t_next += T_s + pll.correction()
        send_t.clear()
        # start the firmware's timing statistics afresh (its TIMING reply resets them)
        # and arm, both in the stream: the scenario's first frame follows
        link.send(M.BY_NAME["request"](msg_id=T.TIMING))
        link.send(M.BY_NAME["arm"]())
        t0 = clock()
        steal0 = steal_seconds()
        ref_prev = sim.x_ref()
        for k in range(n):
            _sleep_until(t_next)
            ref = float(x_ref_at(k * sim.Ts))
            if ref != ref_prev:
                self._set_ref(ref)
                ref_prev = ref
            send_t[k] = clock()
            self._sensor(k, *sim.read())
            a = pump(t_next + T_s * 0.85, k)
            if a is None:
                late[k] = 1
            else:
                state["duty"] = a.duty
                fw_state[k] = a.state
                fw_faults[k] = a.faults
            if k and a is None:
                fw_state[k] = fw_state[k - 1]
                fw_faults[k] = fw_faults[k - 1]
            sim.step(state["duty"])
            t_next += T_s + pll.correction()
            if progress is not None and k % 250 == 0:
                progress(k, n)
            if self.board is not None and k % 500 == 0:
                self._check_board()
        wall = clock() - t0
        steal = steal_seconds() - steal0
        if progress is not None:
            progress(n, n)
        pump(clock() + 0.02, None)
        stats = self.finish()
        _drain(link, sink, n)
        log = sim.result()
        log.update(fw_state=fw_state, fw_faults=fw_faults, latency_us=latency, late=late)
        stats.update(sink.stats())
        lat = latency[np.isfinite(latency)]
        period_us = T_s * 1e6
        stats.update({
            "ticks": n,
            "gains": self.gains,
            "late": int(late.sum()),
            "answered": int(lat.size),
            "latency_us_mean": float(lat.mean()) if lat.size else math.nan,
            "latency_us_max": float(lat.max()) if lat.size else math.nan,
            "latency_us_p99": float(np.percentile(lat, 99)) if lat.size else math.nan,
            "period_us": period_us,
            "wall_s": wall,
            "steal_s": steal,
            "fw_realtime_policy": bool(self.board.realtime_policy) if self.board is not None else None,
            "host_realtime_policy": host_rt,
        })
        return HilRun(scenario, sim.params, log, "realtime", self.link_kind, wall, stats)

    def run(self, scenario: Scenario, params: RobotParams | None = None, **kwargs: Any) -> HilRun:
        """Run one scenario in the session's mode."""
        if self.mode == "lockstep":
            return self.run_lockstep(scenario, params, **kwargs)
        return self.run_realtime(scenario, params, **kwargs)


_FAULT_STATE = next(code for code, name, _ in T.STATES if name == "fault")

_TABLES: dict[tuple[int | None, tuple[float, float] | None], tuple[bytes, str]] = {}


def _gain_table(encj: int | None, sigma: tuple[float, float] | None = None) -> tuple[bytes, str]:
    # the design's table (host/design/export.py, default robot) with the estimator designed for
    # measurement noise `sigma` and ENCJ replaced
    key = (encj, sigma)
    if key not in _TABLES:
        from host.design.discrete import controller_ss
        from host.design.export import export

        labels = []
        if sigma is None:
            fd = export()
        else:
            fd = export(ctrl=controller_ss(load_params(), sigma_meas=sigma))
            labels.append(f"estimator for noise {sigma[0]:.3g} m / {sigma[1]:.3g} rad")
        if encj is not None:
            fd.tables["ENCJ"] = [int(encj)]
            labels.append(f"encoder step limit {encj} counts/tick")
        _TABLES[key] = (fd.blob(), ", ".join(labels) or "firmware default")
    return _TABLES[key]


def design_noise(scenario: Scenario, params: RobotParams) -> tuple[float, float] | None:
    """Measurement noise ``(m, rad)`` the estimator is designed for in this scenario, or
    ``None`` when the firmware's own table (default sensor noise) serves.

    See :func:`host.design.discrete.sigma_meas_for`.
    """
    from host.design.discrete import SIGMA_MEAS, sigma_meas_for

    sig = sigma_meas_for(scenario, params)
    return None if sig == tuple(SIGMA_MEAS) else sig


def encoder_jump_limit(scenario: Scenario, params: RobotParams) -> int | None:
    """Encoder plausibility limit (counts per tick) a noisy scenario needs, or ``None``.

    The firmware faults (``F_ENC_JUMP``) when two encoder readings differ by more than the
    cart can move in one tick (2x its no-load speed).  Measurement noise on the cart
    position -- which a real quadrature encoder does not have, but the report's noise
    scenarios add "on both outputs" -- makes consecutive readings differ by up to twice
    the noise amplitude (uniform) or about 9 sigma (white, Gaussian: 6 sigma of a
    difference).  When that exceeds the default limit, the limit is widened by it.

    Returns
    -------
    int or None
        The widened limit, or ``None`` when the default table serves.
    """
    from sim.sensors import enc_counts_per_m

    n = scenario.noise
    if n.kind == "none" or "x" not in n.channels:
        return None
    p = scenario.apply(params)
    cpm = enc_counts_per_m(p)
    if n.kind == "uniform":
        spread = 2.0 * n.amplitude * cpm
    else:
        spread = 9.0 * n.std(1.0 / p.rate) * cpm
    base = 2.0 * p.V_supply * p.r_wheel / (p.kt * p.gear) / p.rate * cpm + 2.0
    if spread < 1.0:
        return None
    return int(min(30000, math.ceil(base + spread + 2)))


def _cause(exc: BaseException) -> str:
    c = exc.__cause__ or exc
    s = str(c).strip().splitlines()
    return s[0] if s else type(c).__name__


def _drain(link: Link, sink: "_Sink", tick: int, seconds: float = 0.05) -> None:
    # hand what is waiting to the sink; bounded in time, as a board in real time (or one
    # sending heartbeats) never stops talking
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        m = link.recv(0.0)
        if m is None:
            return
        sink.other(m, tick)


def _peek(sim: PlantSim, j: int) -> tuple[int, int]:
    # the (adc, enc) the board will read j ticks from now, 1 <= j <= delay_steps: taken
    # at tick now + j - delay <= now, so it is already in the sensor delay line
    peek = getattr(sim, "peek", None)
    if peek is not None:
        return peek(j)
    line = sim.sensor_model._line
    d = line.steps
    if not 1 <= j <= d:
        raise ValueError(f"can only look 1..{d} ticks ahead, asked {j}")
    enc, adc = line._buf[(line._i + j - 1) % d]
    return int(adc), int(enc)


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


class _Sink:
    # everything but actuator frames: telemetry (sequence-checked), heartbeats, acks.
    # `link`: the link the messages come from; its last_seq (serial) is read for each
    # message handed over, right after that message's recv
    def __init__(self, link: Link | None = None) -> None:
        from host.hil.faults import SeqAccount

        self._link = link
        self.acct = SeqAccount()
        self.telemetry = 0
        self.step_us: list[int] = []
        self.heartbeats = 0
        self.acks = 0
        self.nacks: list[str] = []
        self.last_state: int | None = None
        self.last_faults = 0
        self._last_seq: int | None = None
        self.other_msgs = 0

    def other(self, m: Any, tick: int = -1) -> None:
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
        elif t is _NACK:
            self.nacks.append(f"tick {tick}: {m}")
            if m.msg_id in (T.HIL_SENSOR, T.SET_REFERENCE):
                raise HilError(f"the firmware refused a loop frame at tick {tick}: {m}")
        else:
            self.other_msgs += 1

    def stats(self) -> dict[str, Any]:
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


# ---------------------------------------------------------------- many scenarios
def resolve_scenarios(spec: str | Sequence[str]) -> list[Scenario]:
    """Scenarios from ``"all"`` (the report's), a name, a TOML path, or a list of those.

    Raises
    ------
    sim.scenario.ScenarioError
        Unknown name or invalid file (the message lists the known scenarios).
    """
    names: list[str]
    if isinstance(spec, str):
        names = [s for s in spec.split(",") if s] if spec != "all" else [n for n in REPORT_SCENARIOS if n in list_scenarios()]
    else:
        names = list(spec)
    return [load_scenario(n) for n in names]


def write_outputs(run: HilRun, out: str | Path, *, gif: bool = True, plot: bool = True) -> dict[str, Path]:
    """Write ``<name>.csv``, ``<name>.png`` and ``<name>.gif`` of a run into ``out``.

    Returns
    -------
    dict
        ``{"csv": path, "png": path, "gif": path}`` (those written).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    paths["csv"] = write_csv(run.log, out / f"{run.name}.csv")
    if plot or gif:
        from sim import plots

        summ = run.summary()
        label = f"HIL ({run.link}, {run.mode})"
        if plot:
            overlay = {"float simulation": run.reference} if run.reference is not None else None
            paths["png"] = plots.plot_run(run.log, out / f"{run.name}.png", run.params,
                                          title=f"{run.name}: firmware in the loop, {run.link} link, {run.mode}",
                                          overlay=overlay, label=label, settling_time=summ.metrics.settling_time)
        if gif:
            paths["gif"] = plots.animate_run(run.log, out / f"{run.name}.gif", run.params,
                                             title=f"{run.name} (firmware in the loop)")
    return paths


def float_reference(scenario: Scenario, params: RobotParams, *, init: str = "measured",
                    seed: int | None = None, ctrl: Any = None) -> dict[str, np.ndarray]:
    """The same scenario closed with the float discrete design in pure simulation.

    The controller is :func:`host.design.discrete.controller_for` of the *design* parameters
    ``params`` (the gains the firmware carries, with the estimator designed for the
    scenario's measurement noise as :meth:`HilSession.prepare` uploads it); the plant
    gets the scenario's overrides.
    The loop is :func:`sim.plantsim.run_scenario_float`'s, with one choice added:

    Parameters
    ----------
    scenario : Scenario
        The scenario.
    params : RobotParams
        Design (and base plant) parameters.
    init : {"measured", "zero"}
        Initial controller state.  ``"measured"`` (default) starts it the way the firmware
        does when balancing starts: the estimate of the (delayed) state is the first
        measurement -- tilt from the ADC, cart position 0 (the firmware zeroes its
        encoder position then), speeds 0 -- and the stored forces are empty.  ``"zero"``
        starts from ``z = 0`` exactly as :func:`~sim.plantsim.run_scenario_float` (a test
        checks the two agree to the last bit).
    seed : int, optional
        Noise seed overriding the scenario's.
    ctrl : DiscreteController, optional
        Another design (the one whose table :meth:`HilSession.use_gains` uploaded).

    Returns
    -------
    dict of ndarray
        The run log, like :func:`~sim.plantsim.run_scenario_float`'s.
    """
    from host.design.discrete import controller_for
    from sim import motor, sensors

    if init not in ("measured", "zero"):
        raise ValueError(f"init must be 'measured' or 'zero', got {init!r}")
    ctrl = controller_for(scenario, params) if ctrl is None else ctrl
    sim = PlantSim(params, scenario, seed=seed)
    p = sim.params
    Ac, Bc, Cc, Dc = (np.asarray(m, dtype=float) for m in (ctrl.Ac, ctrl.Bc, ctrl.Cc, ctrl.Dc))
    Bu = np.asarray(ctrl.Bu, dtype=float)[:, 0]
    umax = float(ctrl.u_max)
    nz = Ac.shape[0]
    # the speed estimate is linear in (z, v): probe its rows once
    Ez = np.array([ctrl.estimate(np.eye(nz)[i], np.zeros(3))[1] for i in range(nz)])
    Ev = np.array([ctrl.estimate(np.zeros(nz), np.eye(3)[i])[1] for i in range(3)])
    cpm = sensors.enc_counts_per_m(p)
    cpr = sensors.adc_counts_per_rad(p)
    adc0, enc0 = sim.read()
    unwrap = sensors.EncoderUnwrapper(enc0)
    z = np.zeros(nz)
    x_origin = 0.0
    if init == "measured":
        x_origin = float(unwrap.update(enc0)) / cpm
        unwrap = sensors.EncoderUnwrapper(enc0, origin=enc0)
        z[2] = (adc0 - p.pot_offset) / cpr
    extra: dict[str, list[float]] = {"x_meas": [], "phi_meas": [], "xdot_est": []}
    for _ in range(sim.n_ticks):
        adc, enc = sim.read()
        xm = float(unwrap.update(enc)) / cpm
        phm = (adc - p.pot_offset) / cpr
        v = np.array([xm, phm, sim.x_ref() - x_origin])
        u = float(Cc[0] @ z + Dc[0] @ v)
        us = min(max(u, -umax), umax)
        xd = float(Ez @ z + Ev @ v)
        duty = int(motor.duty_from_force(us, xd, p))
        z = Ac @ z + Bc @ v + Bu * us
        sim.step(duty, u_cmd=u, u_sat=us)
        extra["x_meas"].append(xm)
        extra["phi_meas"].append(phm)
        extra["xdot_est"].append(xd)
    out = sim.result()
    out.update({k: np.asarray(v) for k, v in extra.items()})
    return out


def run_scenarios(scenarios: Sequence[Scenario], *, port: str | None = None, link: str = "serial",
                  mode: str = "lockstep", out: str | Path | None = None, params: RobotParams | None = None,
                  compare: bool = False, gif: bool = True, plot: bool = True,
                  progress: Callable[[str, int, int], None] | None = None, **session_kw: Any) -> list[HilRun]:
    """Run scenarios through one HIL session and write their outputs.

    Parameters
    ----------
    scenarios : sequence of Scenario
        What to run, in order.
    port, link, mode
        See :class:`HilSession` (``port=None``: the virtual board).
    out : str or Path, optional
        Directory for CSV/PNG/GIF (nothing written when ``None``).
    params : RobotParams, optional
        Robot parameters (default ``sim/robot.toml``).
    compare : bool
        Also run the float pure simulation and keep it in ``HilRun.reference``.
    gif, plot : bool
        Write the GIF / PNG.
    progress : callable, optional
        ``progress(scenario_name, tick, n_ticks)``.
    **session_kw
        Passed to :class:`HilSession`.
    """
    params = params or load_params()
    runs: list[HilRun] = []
    with HilSession(port, link=link, mode=mode, **session_kw) as sess:
        for sc in scenarios:
            cb = (lambda k, n, _name=sc.name: progress(_name, k, n)) if progress else None
            run = sess.run(sc, params, progress=cb)
            if compare:
                run.reference = float_reference(sc, params)
            if out is not None:
                run.stats["files"] = {k: str(v) for k, v in write_outputs(run, out, gif=gif, plot=plot).items()}
            runs.append(run)
    return runs
