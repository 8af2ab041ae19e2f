"""Hardware-in-the-loop session: one connection to a board running the firmware's HIL main.

A :class:`HilSession` owns one connection to a board running the firmware's HIL main
(:mod:`firmware.main_hil`): a real board on a serial port or CAN channel, or the virtual
board -- the MicroPython unix port on a pty (:mod:`host.boards.vport`).  It opens and closes
the link (and the virtual board), brings the board to a clean start for each scenario
(:meth:`HilSession.prepare`), uploads the gain table the scenario needs
(:mod:`host.hil.gains`), and runs a scenario of :class:`sim.plantsim.PlantSim` against the
firmware, tick by tick, in one of two modes:

lockstep (deterministic; :meth:`HilSession.run_lockstep`)
    THE lockstep loop, :class:`host.hil.lockstep.Lockstep`: one sensor frame, one answer,
    one plant step per tick, sensor frames pipelined ahead of the board, every tick checked.
real time (:meth:`HilSession.run_realtime`)
    The firmware paces its own loop; the host streams one frame per period, phase-locked
    (:mod:`host.hil.realtime`).

Before each scenario the board is disarmed, its faults cleared, the arm threshold opened
(``arm_tilt_mrad`` = its maximum, so a large initial tilt is caught), the reference set,
one priming sensor frame with the initial reading sent (tick :data:`PRIME_TICK`), then
armed; the reference follows the scenario with ``set_reference`` frames placed in the
stream just before the tick they apply to.

A fault-injection hook (``fault_tx``/``fault_rx``, see :class:`FaultyPort`) sits in the
host-side link path: it can corrupt, drop or duplicate bytes in either direction without
touching the firmware or the protocol code (:mod:`host.hil.faults` has the injectors).
Many scenarios with their files: :mod:`host.hil.runs`; the float reference:
:mod:`host.hil.reference`.
"""

from __future__ import annotations

import time
from typing import Any, Callable, Mapping, Sequence

from firmware import msgtable as T
from host.boards.vport import PTMX, PortError, VirtualBoard, open_can, slave_of
from host.hil.accounting import Sink
from host.hil.answer_time import BASE_S, answer_time, board_speed, describe, first_answer
from host.hil.errors import HilError, TickError
from host.hil.gains import design_noise, encoder_jump_limit, gain_table
from host.hil.lockstep import PRIME_TICK, Lockstep
from host.hil.realtime import run_realtime
from host.hil.results import HilRun
from host.link import messages as M
from host.link.clients import BOARD_BAUD, CanLink, CommandRefused, Link, LinkError, SerialLink
from sim.params import RobotParams, load_params
from sim.plantsim import PlantSim
from sim.scenario import Scenario

__all__ = [
    "HilSession",
    "FaultyPort",
    "install_fault",
    "PRIME_TICK",
    "LINKS",
    "MODES",
]

LINKS = ("serial", "can")
MODES = ("lockstep", "realtime")

_SENSOR = M.BY_NAME["hil_sensor"]
_ACTUATOR = M.BY_NAME["hil_actuator"]
_SET_REF = M.BY_NAME["set_reference"]
_ARM_TILT_MAX = next(p[4] for p in T.PARAMS if p[0] == T.P_ARM_TILT)


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


def install_fault(link: Link, tx: Callable[[bytes], bytes] | None, rx: Callable[[bytes], bytes] | None) -> None:
    """Put a :class:`FaultyPort` with hooks ``tx``/``rx`` under a byte-stream link.

    Raises
    ------
    HilError
        The link is not on a byte stream (a CAN bus other than python-can's ``serial``).
    """
    # SerialLink keeps its pyserial port in ._ser; python-can's serial bus in .bus._ser
    holder = link.bus if isinstance(link, CanLink) else link
    inner = getattr(holder, "_ser", None)
    if inner is None:
        raise HilError(f"fault injection needs a byte-stream link, not {type(holder).__name__}")
    holder._ser = FaultyPort(inner, tx=tx, rx=rx)


def _cause(exc: BaseException) -> str:
    c = exc.__cause__ or exc
    s = str(c).strip().splitlines()
    return s[0] if s else type(c).__name__


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
    timeout : float or None
        Seconds (wall) to wait for any one answer of the firmware; ``None`` for a real port:
        2 s scaled by the board's clock measured against the wall's when the session opens
        (:mod:`host.hil.answer_time`: an emulated board under load gets longer), 2 s for the
        virtual board.
    answer_timeout : float
        Real port: seconds (wall) for the board to answer at all when the session opens.
    notice : callable, optional
        ``notice(line)``: what the session measured on opening (the board's speed, the answer
        time), for a progress display.
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
    probe : bool
        Virtual board: run the probed HIL main (:func:`host.boards.vport.probe_code`: the
        heap locked for the whole lockstep run, heap and decoder counters reported at
        exit); read the report with :meth:`probe` after :meth:`close`.

    Raises
    ------
    ValueError
        Unknown link or mode, or ``probe`` with a real board.
    """

    def __init__(self, port: str | None = None, *, link: str = "serial", mode: str = "lockstep", node: int = 1,
                 can_interface: str = "serial", baudrate: int = BOARD_BAUD, timeout: float | None = 2.0,
                 answer_timeout: float = 10.0, notice: Callable[[str], None] | None = None,
                 fault_tx: Callable[[bytes], bytes] | None = None, fault_rx: Callable[[bytes], bytes] | None = None,
                 heapsize: str | None = None, rt_priority: int | None = 20, heap_lock: bool = False,
                 probe: bool = False) -> None:
        if link not in LINKS:
            raise ValueError(f"link must be one of {', '.join(LINKS)}, got {link!r}")
        if mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
        if not 0 <= int(node) < 2**T.NODE_BITS:
            raise ValueError(f"node must be in 0..{2**T.NODE_BITS - 1}, got {node!r}")
        if timeout is not None and not timeout > 0:
            raise ValueError(f"timeout must be > 0, got {timeout!r}")
        if not answer_timeout > 0:
            raise ValueError(f"answer_timeout must be > 0, got {answer_timeout!r}")
        if probe and port is not None:
            raise ValueError("probe runs on the virtual board only (port=None)")
        self.port = port
        self.link_kind = link
        self.mode = mode
        self.node = int(node)
        self.can_interface = can_interface
        self.baudrate = int(baudrate)
        # None: measured at open() (a real port), else 2 s
        self.timeout = BASE_S if timeout is None and port is None else timeout  # type: ignore[assignment]
        self.answer_timeout = float(answer_timeout)
        self.speed: float | None = None  # the board's clock / the wall's, when measured
        self._notice = notice
        self.heapsize = heapsize
        self.rt_priority = rt_priority
        self.heap_lock = bool(heap_lock)
        self.probed = bool(probe)
        self._probe: dict[str, int] | None = None
        self._board_tail = ""
        self.returncode: int | None = None
        self._fault = (fault_tx, fault_rx)
        self.link: Link | None = None
        self.board: VirtualBoard | None = None
        self._bus: Any = None
        self._table_key: Any = (None, None)
        self._gains_label = "firmware default"
        self.gains = self._gains_label
        self._custom: tuple[bytes, str] | None = None
        self._switched = False  # open() sent MODE hil to a real board

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
                    # port's own: CanLink waits for the first byte itself and sets the port's
                    # timeout to the rest of a frame's (STREAM_FRAME_WAIT_S, host.link.clients)
                    self._bus = open_can(PTMX, interface="serial")
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
                                          probe=self.probed)
                self.board.start()
            if any(self._fault):
                install_fault(self.link, *self._fault)
            if not self.virtual:
                self._answer_time()
            if not self.virtual and self.link_kind == "serial" and self.mode == "lockstep":
                self._enter_hil()
        except BaseException:
            self.close()
            raise
        return self

    def _answer_time(self) -> None:
        # a real port: wait for the board's first answer; without a fixed timeout, scale the
        # answer time by the board's clock (an emulated Pico runs at 0.05-0.4x real time)
        try:
            first = first_answer(self._link(), str(self.port), self.answer_timeout)
            if self.timeout is None:
                self.speed = board_speed(self._link(), first, timeout=self.answer_timeout)
                self.timeout = answer_time(self.speed)
                if self._notice is not None:
                    self._notice(describe(self.speed, self.timeout))
        except CommandRefused as exc:
            raise HilError(f"the board on {self.port} refused a heartbeat request ({exc})") from exc
        except LinkError as exc:
            raise HilError(f"no answer from {self.port}: {exc}") from exc

    def _enter_hil(self) -> None:
        # a board flashed with `make flash` runs the robot at boot: MODE hil hands its link to
        # the lockstep HIL main (firmware/main.py, no reflash); one already in HIL mode ACKs it
        try:
            self._link().request(M.BY_NAME["mode"](mode=T.MODE_HIL), timeout=self.timeout / 4, retries=3)
        except CommandRefused as exc:
            raise HilError(f"the board on {self.port} refused HIL mode ({exc}): disarm it first") from exc
        except LinkError as exc:
            raise HilError(f"no answer to MODE hil from {self.port}: {exc}") from exc
        self._switched = True

    def _leave_hil(self) -> None:
        # back to the robot (best effort: the board may be gone; a reset does the same)
        self._switched = False
        link = self.link
        if link is None:
            return
        for msg in (M.BY_NAME["disarm"](), M.BY_NAME["mode"](mode=T.MODE_ROBOT)):
            try:
                link.request(msg, timeout=self.timeout / 4, retries=1)
            except LinkError:
                return

    def close(self) -> None:
        """Close the link and stop the virtual board (idempotent); a real board switched to HIL
        mode by :meth:`open` goes back to robot mode."""
        if self._switched:
            self._leave_hil()
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
            self.returncode = self.board.returncode
            if self.probed:
                self._probe = self.board.probe_report()
                self._board_tail = " | ".join(self.board.output().strip().splitlines()[-4:])

    def probe(self) -> dict[str, int]:
        """The probed firmware's exit report (``probe=True``, after :meth:`close`).

        Raises
        ------
        HilError
            If the firmware did not report (it crashed: e.g. ``MemoryError`` under the
            heap lock); the message holds its output tail.
        """
        if not self.probed:
            raise HilError("this session's board is not probed (probe=False)")
        if self._probe is None:
            raise HilError(f"the firmware did not report at exit: {self._board_tail or '(no output)'}")
        return dict(self._probe)

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

    def _await_actuator(self, tick: int, sink: Sink) -> Any:
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
        blob, label = self._custom if self._custom is not None else gain_table(encj, sigma)
        try:
            self._link().upload_gains(blob, timeout=self.timeout / 4, retries=3)
        except LinkError as exc:
            self._check_board()
            raise HilError(f"gain table upload ({label}) failed: {exc}") from exc
        self._table_key = key
        self._gains_label = label
        return label

    def prepare(self, sim: PlantSim, sink: Sink | None = None, *, arm: bool = True,
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
        sink = sink or Sink()
        self._request(link.disarm)
        if not link.heartbeat_running:
            # the controlling host's heartbeat feeds the board's link watchdog while connected
            link.start_heartbeat()
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
        sink.drain(link, -1)

    def finish(self) -> dict[str, int]:
        """Disarm after a run and read the firmware's timing statistics."""
        link = self._link()
        self._request(link.disarm)
        try:
            t = self._request(link.query, "timing")
        except (CommandRefused, HilError):
            return {}
        return {f"fw_{k}": int(v) for k, v in zip((f.name for f in t.FIELDS), t.values())}

    # ------------------------------------------------------------------ runs
    def run_lockstep(self, scenario: Scenario, params: RobotParams | None = None, *, pipeline: int | None = None,
                     progress: Callable[[int, int], None] | None = None, seed: int | None = None,
                     x0: Sequence[float] | None = None, fw_params: Mapping[str | int, int] | None = None) -> HilRun:
        """Run one scenario in lockstep (deterministic; :class:`host.hil.lockstep.Lockstep`, strict).

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
        link = self._link()
        sink = Sink(link)
        self.prepare(sim, sink, fw_params=fw_params)
        d = sim.sensor_model.delay_steps
        depth = d if pipeline is None else max(0, min(int(pipeline), d))
        loop = Lockstep(self, sim, sink=sink, depth=depth, progress=progress).run()
        stats = self.finish()
        sink.drain(link, loop.n)
        log = loop.log("fw_state", "fw_faults")
        stats.update(sink.stats())
        stats.update({"ticks": loop.n, "gains": self.gains, "pipeline": depth, "plant_s": loop.t_plant,
                      "link_s": loop.t_link, "wall_s": loop.wall})
        return HilRun(scenario, sim.params, log, "lockstep", self.link_kind, loop.wall, stats)

    def run_realtime(self, scenario: Scenario, params: RobotParams | None = None, *, lead: float = 0.5,
                     sync_ticks: int = 100, progress: Callable[[int, int], None] | None = None,
                     seed: int | None = None, x0: Sequence[float] | None = None,
                     fw_params: Mapping[str | int, int] | None = None) -> HilRun:
        """Run one scenario in real time (the firmware paces itself; :mod:`host.hil.realtime`).

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
        return run_realtime(self, scenario, params, lead=lead, sync_ticks=sync_ticks, progress=progress,
                            seed=seed, x0=x0, fw_params=fw_params)

    def run(self, scenario: Scenario, params: RobotParams | None = None, **kwargs: Any) -> HilRun:
        """Run one scenario in the session's mode."""
        if self.mode == "lockstep":
            return self.run_lockstep(scenario, params, **kwargs)
        return self.run_realtime(scenario, params, **kwargs)
