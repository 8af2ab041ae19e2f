"""HIL on the emulated RP2040: the unchanged board firmware closed around the plant at its pins.

The board is :class:`host.boards.rp2040.board.EmulatedBoard` running the bundle's ``main.py``
-- ``HalPico``, the paced ``App.run()`` with the heap locked, the UART0 host link at 1 Mbaud --
exactly what a Pico runs after ``make flash``.  Nothing reaches it through link frames but what
a host sends a real board (``disarm``, ``clear_faults``, a gain table when the scenario's noise
needs one, ``param_set``, ``set_reference``, ``arm`` with the board's arming epoch and the
``host_heartbeat`` that feeds the link watchdog);
the sensors and the motor are its pins, in lock-step with emulated time:

each plant tick k (the control period ``Ts`` of :class:`sim.plantsim.PlantSim`)
    the ADC0 input is set to the potentiometer reading of ``PlantSim.read()`` (the project's
    sensor model: offset, scale, noise, 12 bits, measurement delay) and the quadrature encoder
    is driven to the count of that reading (the harness generates the A/B edges, PIO decodes
    them); the board runs ``Ts`` of emulated time; the motor command is read back from the PWM
    slice (compare / top), the DIR and the EN pins with their change history, and the duty
    actually applied, averaged over the tick (the motor force is linear in the duty), is what
    ``PlantSim.step`` integrates, with the part of the tick EN was high (EN low: the bridge's
    outputs off, no drive and no back-EMF braking -- the motor coasts, as on the virtual robot).

The plant's ticks are aligned to the firmware's: its loop iterations are found from the
outside (the loop probe of the harness: ``App.run`` busy-waits on the TIMER between
iterations) and each plant tick starts :attr:`EmulatedHil.margin_us` before an iteration, so
the encoder edges (generated in the first ``enc_within_us`` of the tick) are in before the
firmware reads its sensors.  The firmware's duty then takes effect after its own computing
time, within the tick -- the board's real latency, which the lockstep ``--virtual`` runs do
not have.

Host frames are written at the emulated time the scenario says: a reference change for tick
k+1 at the start of tick k (the firmware applies commands in the link poll after its step),
``arm`` one tick before the scenario's first, ``host_heartbeat`` every
:attr:`EmulatedHil.keepalive_ms` (as :meth:`host.link.clients.Link.start_heartbeat` does).
``App.run`` balances only once it has measured :data:`WARMUP_PERIODS` on-time loop periods in a
row (since it started, or since a late tick while disarmed), so the host arms only after the
loop probe has seen that many: arming a board that has just booted (or whose set-up made a tick
late) would start balancing ticks after the scenario's start.  Telemetry and heartbeats are
decoded from UART0 and accounted for (:class:`host.hil.accounting.Sink`); the supervisor state per tick
(``fw_state``) is the last heartbeat's.  The tick time reported (``tick_us_*``) is the whole
loop iteration (step + link poll) measured in emulated cycles at 125 MHz; the firmware's own
``step_us`` (telemetry) covers the control step only.

Errors: a board that does not boot or raises is a :class:`~host.boards.rp2040.board.BoardError`
quoting the board's last output; a loop that stops ticking or a command the board does not
answer is a :class:`~host.hil.errors.HilError` with the same quote.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from firmware import app as _fwapp
from firmware import msgtable as T
from host.boards.rp2040.board import CYCLES_PER_US, FIRMWARE, BoardError, EmulatedBoard, StepResult
from host.hil.accounting import Sink
from host.hil.errors import HilError
from host.hil.gains import design_noise, encoder_jump_limit, gain_table
from host.hil.reference import float_reference
from host.hil.results import HilRun
from host.link import messages as M
from sim import sensors
from sim.motor import DUTY_MAX
from sim.params import RobotParams, load_params
from sim.plantsim import PlantSim
from sim.scenario import Scenario

__all__ = ["EmulatedHil", "PinDrive", "run_emulated", "duty_over", "BoardError"]

EDGE_US = 0.25
"""Shortest spacing of two generated encoder edges (us; 31 cycles, several PIO sampling passes).
The harness keeps its edges at least this far apart whatever it is asked (``ENC_GAP_NS`` in
``host/boards/rp2040/harness.mjs``: a larger jump goes on into the following runs)."""
_ARM_TILT_MAX = next(p[4] for p in T.PARAMS if p[0] == T.P_ARM_TILT)
WARMUP_PERIODS = int(getattr(_fwapp, "_WARMUP", 16))
"""On-time loop periods ``App.run`` measures before ARMED may balance (``firmware/app.py``)."""
_LATE = 1.5
"""A loop period longer than this many nominal periods is late (``App._period``)."""
_HOST_HEARTBEAT = M.BY_NAME["host_heartbeat"]
_HEARTBEAT = M.BY_NAME["heartbeat"]
_ACK = M.BY_NAME["ack"]
_NACK = M.BY_NAME["nack"]
_REPLY = {"param_set": "param_value", "param_get": "param_value"}


def duty_over(state: dict[str, Any], r: StepResult, c0: int, c1: int, *, pwm_pin_top: bool = True) -> float:
    """Average signed duty (``-32767..32767`` counts) the H-bridge applied over cycles ``[c0, c1)``.

    ``state`` holds the motor pins at ``c0`` (``compare``, ``top``, ``enabled``, ``dir``,
    ``en``) and is updated to their values at ``c1`` from the interval's PWM register writes and
    DIR/EN edges (``r.pwm_events``, ``r.edges``).  The magnitude is ``compare / (top + 1)`` of the
    PWM period (``HalPico.set_motor`` writes ``duty_u16(duty << 1)``), negative with DIR high,
    0 with the slice disabled or EN low.  ``state["en_frac"]`` is set to the fraction of the
    interval EN was high: the H-bridge drives (a duty, or slow-decay braking at duty 0) only then;
    with EN low its outputs are off and the motor coasts (``PlantSim.step(driven=...)``).
    """
    ev: list[tuple[int, int, Any]] = []
    for cyc, cmp_, top, en, _div in r.pwm_events:
        ev.append((cyc, 0, (cmp_, top, en)))
    for pin, cyc, level in r.edges:
        ev.append((cyc, 1, (pin, level)))
    ev.sort(key=lambda e: (e[0], e[1]))

    def level() -> float:
        if not state["enabled"] or not state["en"]:
            return 0.0
        frac = min(1.0, state["compare"] / (state["top"] + 1))
        mag = frac * (2 * DUTY_MAX + 1) / 2.0
        return -mag if state["dir"] else mag

    acc = 0.0
    on = 0  # cycles with EN high
    t = c0
    for cyc, kind, val in ev:
        cyc = min(max(cyc, c0), c1)
        acc += level() * (cyc - t)
        if state["en"]:
            on += cyc - t
        t = cyc
        if kind == 0:
            state["compare"], state["top"], state["enabled"] = val[0], val[1], bool(val[2])
        elif val[0] == state["dir_pin"]:
            state["dir"] = val[1] or 0
        elif val[0] == state["en_pin"]:
            state["en"] = val[1] or 0
    acc += level() * (c1 - t)
    if state["en"]:
        on += c1 - t
    state["en_frac"] = on / max(1, c1 - c0) if c1 > c0 else float(bool(state["en"]))
    # the values in force at the end (the harness's own view, in case an event was missed)
    state["compare"], state["top"], state["enabled"] = r.pwm_compare, r.pwm_top, r.pwm_enabled
    state["dir"], state["en"] = r.dir or 0, r.en or 0
    return acc / max(1, c1 - c0)


class PinDrive:
    """The robot's side of the Pico's pins, as ``firmware/board.py`` wires them: the sensor
    readings of :class:`sim.plantsim.PlantSim` put on ADC0 and the quadrature encoder, the duty
    read back from the PWM slice and the DIR/EN pins (:func:`duty_over`).  Shared by
    :class:`EmulatedHil` and the virtual robot (:mod:`host.hil.virtual_robot`).

    Parameters
    ----------
    board : EmulatedBoard
        The board (or a proxy with ``set_adc`` / ``set_encoder``: :class:`~host.boards.rp2040.can.CanBoard`).
    enc_within_us : float
        The encoder edges of a reading are generated within this long of the next run's start
        (or at :data:`EDGE_US` per edge for a larger jump).
    lazy : bool
        Write a pin only when its value changed (the virtual robot, many short runs); ``False``
        writes both every time (the lockstep HIL, which also sets pins between runs).
    """

    def __init__(self, board: Any, *, enc_within_us: float = 40.0, lazy: bool = False) -> None:
        from firmware import board as fwboard

        self.board = board
        self.enc_within_us = float(enc_within_us)
        self.lazy = bool(lazy)
        self.motor: dict[str, Any] = {"compare": 0, "top": 0, "enabled": False, "dir": 0, "en": 0,
                                      "dir_pin": fwboard.DIR_PIN, "en_pin": fwboard.EN_PIN}
        self.enc_total = 0  # the position handed to the harness (x4 counts since its start)
        self._enc_last = 0
        self._adc: int | None = None

    def set(self, adc: int, enc: int) -> None:
        """Put a reading on the pins for the next run: ADC counts and the 16-bit encoder counter
        (unwrapped: the harness drives the absolute position)."""
        d = int(sensors.encoder_delta(enc, self._enc_last))
        self.enc_total += d
        self._enc_last = int(enc)
        if not self.lazy or adc != self._adc:
            self.board.set_adc(int(adc))
            self._adc = int(adc)
        if not self.lazy or d:
            self.board.set_encoder(self.enc_total, within_us=max(self.enc_within_us, abs(d) * EDGE_US))

    def sync(self, r: StepResult) -> None:
        """Take the motor pins' state at the end of run ``r`` (runs not read through
        :meth:`duty`, e.g. the set-up between two scenarios: otherwise the next scenario's first
        tick starts from the last duty the previous one read, whatever the board did since)."""
        m = self.motor
        m["compare"], m["top"], m["enabled"] = r.pwm_compare, r.pwm_top, r.pwm_enabled
        m["dir"], m["en"] = r.dir or 0, r.en or 0
        m.pop("en_frac", None)

    def duty(self, r: StepResult, c0: int, c1: int) -> float:
        """The average duty the H-bridge applied over cycles ``[c0, c1)`` of run ``r``
        (:attr:`en_fraction`: the part of it the bridge was enabled)."""
        return duty_over(self.motor, r, c0, c1)

    @property
    def en_fraction(self) -> float:
        """The fraction of the last :meth:`duty` interval EN was high: what ``PlantSim.step`` takes
        as ``driven`` (EN low: the bridge's outputs off, the motor coasts -- no back-EMF braking)."""
        return float(self.motor.get("en_frac", 1.0 if self.motor["en"] else 0.0))

    @property
    def driving(self) -> bool:
        """The H-bridge drives: the PWM slice on and EN high (the firmware enables the driver only
        while balancing)."""
        m = self.motor
        return bool(m["enabled"] and m["en"])

    def rebase(self) -> None:
        """The board was powered up again (a new harness): its encoder position starts at 0, its
        ADC input is unset, its motor pins are inputs."""
        self.enc_total = 0
        self._adc = None
        self.motor.update(compare=0, top=0, enabled=False, dir=0, en=0)


class _HostSide:
    # the host end of UART0: frames encoded with the project's serial framing, written onto
    # the board's RX line at the current emulated time; the board's TX bytes decoded
    def __init__(self, board: EmulatedBoard) -> None:
        self.board = board
        self.decoder = M.SerialStreamDecoder()
        self.seq = 0
        self.last_seq: int | None = None
        self.sent = 0

    def send(self, msg: M.Message) -> int:
        seq = self.seq
        self.seq = (seq + 1) & 0xFF
        self.board.uart_write(M.encode_serial(msg, seq))
        self.sent += 1
        return seq

    def feed(self, data: bytes) -> list[tuple[M.Message, int]]:
        return self.decoder.feed(data) if data else []


class EmulatedHil:
    """An emulated Pico running ``main.py``, with the plant on its pins (see the module docstring).

    Parameters
    ----------
    bundle_dir : Path, optional
        Firmware bundle (default: built into a temporary directory).
    firmware : Path
        The MicroPython image (``make rp2040``).
    margin_us : float
        A plant tick starts this long before a firmware loop iteration.
    enc_within_us : float
        The encoder edges of a tick are generated within this long of its start -- or, for a
        jump of more counts than fit there at :data:`EDGE_US` per edge (the noise scenarios put
        noise on the encoder reading), spread at that pace: the PIO decoder samples its pins
        every few cycles and must see every state.
    keepalive_ms : float
        Period of the host's ``host_heartbeat`` (the link watchdog is 250 ms).
    reply_ms : float
        Emulated time a command's answer may take (per attempt, 3 attempts).
    stall_ms : float
        No firmware loop iteration for this long: the loop stopped (:class:`HilError`).
    start_ms : float
        The same before the loop's first iteration after :meth:`open`: ``main.py`` builds the
        App first -- its imports, the saved configuration, an older copy migrated and saved
        again (a version-1 copy: 88-110 ms of board time, depending on the firmware's size).
    board : EmulatedBoard, optional
        An already booted board running ``main.py`` (not closed by :meth:`close`).
    """

    def __init__(self, bundle_dir: Path | None = None, *, firmware: Path = FIRMWARE, margin_us: float = 60.0,
                 enc_within_us: float = 40.0, keepalive_ms: float = 50.0, reply_ms: float = 40.0,
                 stall_ms: float = 100.0, start_ms: float = 1000.0, board: EmulatedBoard | None = None) -> None:
        if not 0 < enc_within_us < margin_us:
            raise ValueError("enc_within_us must be in (0, margin_us)")
        self.bundle_dir = bundle_dir
        self.firmware = Path(firmware)
        self.margin_us = float(margin_us)
        self.enc_within_us = float(enc_within_us)
        self.keepalive_ms = float(keepalive_ms)
        self.reply_ms = float(reply_ms)
        self.stall_ms = float(stall_ms)
        self.start_ms = float(start_ms)
        self.board: EmulatedBoard | None = board
        self._own = board is None
        self.host: _HostSide | None = None
        self.boot_wall_s = 0.0
        self._table_key: Any = (None, None)
        self._custom: tuple[bytes, str] | None = None  # use_gains()
        self.gains = "firmware default"
        self.pins: PinDrive | None = None
        self._iters: list[tuple[int, int]] = []
        self._last_iter_end = 0
        self._looping = False  # a loop iteration seen since open(): stall_ms applies, before it start_ms
        self._state = -1
        self._faults = -1

    # ------------------------------------------------------------------ lifetime
    def open(self) -> "EmulatedHil":
        """Boot the board (``main.py``) and switch the loop probe on.

        Raises
        ------
        BoardError
            The board did not boot, or the firmware raised at start-up.
        """
        t0 = time.perf_counter()
        if self.board is None:
            self.board = EmulatedBoard(self.bundle_dir, firmware=self.firmware, main=True)
        self.boot_wall_s = time.perf_counter() - t0
        self.pins = PinDrive(self.board, enc_within_us=self.enc_within_us)
        self.board.loop_probe(gap_us=50.0, min_reads=3)
        self.host = _HostSide(self.board)
        self._last_iter_end = self.board.cycles
        self._looping = False
        return self

    def close(self) -> None:
        """Stop the board (if this object started it)."""
        if self.board is not None and self._own:
            self.board.close()
        self.board = None

    def __enter__(self) -> "EmulatedHil":
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ plumbing
    def _b(self) -> EmulatedBoard:
        if self.board is None or self.host is None:
            raise HilError("emulated board is not open")
        return self.board

    @property
    def measures_supply(self) -> bool:
        """The board firmware measures its motor supply (``firmware/board.py`` ``VSUP_ADC_PIN``
        on an ADC pin, the default): each run puts the simulated robot's supply on that pin, and
        the firmware scales its duty by it as on a real robot."""
        from firmware import board as fb

        return int(getattr(fb, "VSUP_ADC_PIN", -1)) >= 26

    def _tail(self) -> str:
        return self.board.tail() if self.board is not None else ""

    def _set_pins(self, adc: int, enc: int) -> None:
        # the ADC input and the encoder position for the next run (16-bit reading unwrapped)
        self._b()
        assert self.pins is not None
        self.pins.set(adc, enc)

    def _run(self, us: float, sink: Sink | None, tick: int = -1) -> tuple[StepResult, list[tuple[M.Message, int]]]:
        # run the board; decode its UART output; keep the loop iterations; check it still loops
        b = self._b()
        c0 = b.cycles
        r = b.run(us)
        if r.loop_iters:
            self._looping = True
            self._iters.extend(r.loop_iters)
            self._last_iter_end = r.loop_iters[-1][1]
        elif (r.cycles - self._last_iter_end) > (self.stall_ms if self._looping else self.start_ms) * 1000 * CYCLES_PER_US:
            raise HilError(("the firmware loop stopped ticking: no loop iteration for " if self._looping else
                            "the firmware loop did not start: no loop iteration after boot for ")
                           + f"{(r.cycles - self._last_iter_end) / CYCLES_PER_US / 1000:.0f} ms of board time "
                           f"(at {r.cycles / CYCLES_PER_US / 1e6:.3f} s)\n{self._tail()}")
        del c0
        msgs = self.host.feed(r.uart_tx) if self.host is not None else []
        for m, seq in msgs:
            if type(m) is _HEARTBEAT:
                self._state, self._faults = m.state, m.faults
            if sink is not None:
                self.host.last_seq = seq  # type: ignore[union-attr]
                sink.other(m, tick)
        return r, msgs

    def _idle(self, us: float, sink: Sink | None = None) -> list[tuple[M.Message, int]]:
        # run with the pins held (the plant not stepped), in 1 ms pieces
        out: list[tuple[M.Message, int]] = []
        left = float(us)
        while left > 1e-9:
            d = min(1000.0, left)
            out += self._run(d, sink)[1]
            left -= d
        return out

    def request(self, msg: M.Message, *, retries: int = 3, sink: Sink | None = None) -> M.Message:
        """Send a command and run (plant held) until its answer; returns the answer.

        Raises
        ------
        host.link.clients.CommandRefused
            The board answered NACK.
        HilError
            No answer within ``reply_ms`` of board time, ``1 + retries`` times.
        """
        from host.link.clients import CommandRefused

        host = self.host
        assert host is not None
        want = _REPLY.get(msg.NAME, "ack")
        if msg.NAME == "request":
            want = M.MESSAGES[getattr(msg, "msg_id")].NAME
        for _ in range(retries + 1):
            seq = host.send(msg)
            t = 0.0
            while t < self.reply_ms * 1000:
                for m, s in self._run(1000.0, None)[1]:
                    if s == seq and type(m) is _NACK and m.msg_id == msg.ID:
                        raise CommandRefused(m.msg_id, m.reason)
                    if s == seq and (m.NAME == want and (want != "ack" or m.msg_id == msg.ID)):
                        return m
                    if sink is not None:
                        host.last_seq = s
                        sink.other(m, -1)
                t += 1000.0
        raise HilError(f"the board did not answer {msg.NAME} within {self.reply_ms:g} ms of board time "
                       f"({retries + 1} attempts)\n{self._tail()}")

    def use_gains(self, blob: bytes | None, label: str = "custom table") -> None:
        """Run the following scenarios with this gain table (as :meth:`host.hil.session.HilSession.use_gains`).

        ``blob`` is an exported table (``host.design.export.export(...).blob()``), uploaded by the
        next run; ``None`` gives the design's tables (with the scenario's noise adjustments) back.
        """
        self._custom = None if blob is None else (bytes(blob), str(label))

    def _ensure_gains(self, scenario: Scenario, params: RobotParams) -> None:
        custom = self._custom
        key: Any = ("custom", custom) if custom is not None else (encoder_jump_limit(scenario, params),
                                                                    design_noise(scenario, params))
        if key == self._table_key:
            return
        blob, label = custom if custom is not None else gain_table(*key)
        token = self.request(M.BY_NAME["request"](msg_id=T.SESSION)).token  # the upload's session
        self.request(M.BY_NAME["gains_begin"](nbytes=len(blob), crc=M.crc16(blob), token=token))
        n = T.CHUNK_BYTES
        for off in range(0, len(blob), n):
            self.request(M.BY_NAME["gains_chunk"](offset=off, data=blob[off:off + n].ljust(n, b"\x00")))
        self.request(M.BY_NAME["gains_commit"](check=M.table_check(blob)))
        self._table_key = key
        self.gains = label

    def _phase(self, period_us: float, max_ms: float = 1000.0) -> int:
        # cycle of a recent loop iteration start, once the loop has run WARMUP_PERIODS on-time
        # periods in a row (the firmware's timing_ok: an arm before it balances late)
        self._b()
        self._iters.clear()
        self._idle(6000.0)
        if len(self._iters) < 2:
            raise HilError(f"the firmware loop is not running (no loop iterations found)\n{self._tail()}")
        late = _LATE * period_us * CYCLES_PER_US
        waited = 6.0
        while True:
            starts = [s0 for s0, _ in self._iters]
            on_time = 0
            for a, c in zip(starts[-2::-1], starts[:0:-1]):
                if c - a > late:
                    break
                on_time += 1
            if on_time >= WARMUP_PERIODS + 2:
                return starts[-1]
            if waited >= max_ms:
                raise HilError(f"the firmware loop does not keep its period: {on_time} on-time periods in a row "
                               f"after {waited:.0f} ms of board time ({WARMUP_PERIODS} needed to balance)"
                               f"\n{self._tail()}")
            self._idle(2000.0)
            waited += 2.0

    # ------------------------------------------------------------------ one scenario
    def run(self, scenario: Scenario, params: RobotParams | None = None, *,
            progress: Callable[[int, int], None] | None = None, seed: int | None = None,
            x0: Sequence[float] | None = None) -> HilRun:
        """Run one scenario with the plant on the board's pins; returns its :class:`HilRun`.

        ``stats`` holds, besides the telemetry figures of :class:`Sink`: ``tick_us_mean``,
        ``tick_us_max`` (whole loop iterations while the scenario ran, emulated cycles at
        125 MHz), ``period_us``, ``overruns`` (iterations longer than the period),
        ``board_s``, ``emu_speed`` (board seconds per wall second), the firmware's ``timing``
        reply (``fw_*``).

        Raises
        ------
        HilError
            The loop stopped, or the board refused or did not answer a command.
        BoardError
            The board raised or the emulator failed.
        """
        from host.link.clients import CommandRefused

        b = self._b()
        params = params or load_params()
        sim = PlantSim(params, scenario, seed=seed, x0=x0)
        if self.measures_supply:  # the robot's supply on the divider's pin (the scenario's [params] included)
            b.set_supply_mv(1000.0 * float(sim.params.V_supply))
        period_us = sim.Ts * 1e6
        pc = int(round(period_us * CYCLES_PER_US))
        sink = Sink(self.host)
        # the initial reading on the pins, then a clean start (as HilSession.prepare)
        adc0, enc0 = sim.read()
        self._set_pins(adc0, enc0)
        self._idle(10_000.0)
        try:
            self.request(M.BY_NAME["disarm"]())
            self.request(M.BY_NAME["clear_faults"]())
            self._ensure_gains(scenario, params)
            self.request(M.BY_NAME["param_set"](index=T.P_ARM_TILT, value=_ARM_TILT_MAX))
            self.request(M.BY_NAME["set_reference"](x_um=int(round(sim.x_ref() * 1e6))))
            # ARM carries the board's arming token (SESSION; drawn anew by the disarm above)
            epoch = self.request(M.BY_NAME["request"](msg_id=T.SESSION)).token
        except CommandRefused as exc:
            raise HilError(f"the board refused the set-up of {scenario.name}: {exc}\n{self._tail()}") from exc
        # align: plant tick 0 starts margin_us before a loop iteration; arm one tick earlier
        s = self._phase(period_us)
        now = b.cycles
        margin = int(round(self.margin_us * CYCLES_PER_US))
        k = max(0, -(-(now + pc + margin - s) // pc))
        start = s + k * pc - margin  # >= now + pc
        self._idle((start - pc - now) / CYCLES_PER_US)
        self.host.send(M.BY_NAME["arm"](epoch=epoch))  # type: ignore[union-attr]
        self._iters.clear()
        r, _ = self._run((start - b.cycles) / CYCLES_PER_US, sink)
        # the pins as the set-up left them (disarmed since the last scenario: duty 0, EN low)
        assert self.pins is not None
        self.pins.sync(r)
        # the scenario, one plant tick at a time
        n = sim.n_ticks
        fw_state = np.full(n, -1, dtype=np.int64)
        fw_faults = np.full(n, -1, dtype=np.int64)
        x_ref_at = scenario.x_ref
        ref_prev = float(sim.x_ref())
        keep = max(1, int(round(self.keepalive_ms * 1e3 / period_us)))
        t_wall = time.perf_counter()
        c_start = b.cycles
        self._iters.clear()
        pins = self.pins
        assert pins is not None
        for k in range(n):
            adc, enc = sim.read()
            self._set_pins(adc, enc)
            ref = float(x_ref_at((k + 1) * sim.Ts))
            if ref != ref_prev:
                # the reference of tick k+1 (applied in this tick's link poll)
                self.host.send(M.BY_NAME["set_reference"](x_um=int(round(ref * 1e6))))  # type: ignore[union-attr]
                ref_prev = ref
            if k % keep == 0:
                # the host heartbeat that feeds the link watchdog (a real host's Link sends it
                # on its own clock; a set-point only when the reference changes)
                self.host.send(_HOST_HEARTBEAT())  # type: ignore[union-attr]
            c0 = b.cycles
            r, _ = self._run(period_us, sink, k)
            duty = pins.duty(r, c0, r.cycles)
            fw_state[k], fw_faults[k] = self._state, self._faults
            sim.step(int(round(duty)), driven=pins.en_fraction)  # EN low: the motor coasts
            if progress is not None and k % 250 == 0:
                progress(k, n)
        wall = time.perf_counter() - t_wall
        board_s = (b.cycles - c_start) / (CYCLES_PER_US * 1e6)
        iters = [(s0, e0) for s0, e0 in self._iters if s0 >= c_start]
        if progress is not None:
            progress(n, n)
        # disarm, the firmware's own timing statistics
        stats: dict[str, Any] = {}
        try:
            self.request(M.BY_NAME["disarm"](), sink=sink)
            t = self.request(M.BY_NAME["request"](msg_id=T.TIMING), sink=sink)
            stats.update({f"fw_{f.name}": int(v) for f, v in zip(t.FIELDS, t.values())})
        except (CommandRefused, HilError):
            pass
        log = sim.result()
        log["fw_state"] = fw_state
        log["fw_faults"] = fw_faults
        tick_us = np.array([(e0 - s0) / CYCLES_PER_US for s0, e0 in iters]) if iters else np.zeros(0)
        stats.update(sink.stats())
        stats.update({
            "ticks": n, "gains": self.gains, "period_us": period_us,
            "tick_us_mean": float(tick_us.mean()) if tick_us.size else math.nan,
            "tick_us_max": float(tick_us.max()) if tick_us.size else math.nan,
            "tick_us_p99": float(np.percentile(tick_us, 99)) if tick_us.size else math.nan,
            "loop_iterations": int(tick_us.size),
            "overruns": int((tick_us > period_us).sum()),
            "board_s": board_s, "wall_s": wall, "emu_speed": board_s / wall if wall > 0 else math.inf,
            "boot_wall_s": self.boot_wall_s,
        })
        return HilRun(scenario, sim.params, log, "emulated", "uart", wall, stats)


def run_emulated(scenarios: Sequence[Scenario], *, out: str | Path | None = None, params: RobotParams | None = None,
                 compare: bool = True, gif: bool = True, plot: bool = True,
                 progress: Callable[[str, int, int], None] | None = None,
                 on_result: Callable[[HilRun], None] | None = None, bundle_dir: Path | None = None,
                 firmware: Path = FIRMWARE, board: EmulatedBoard | None = None,
                 plant: RobotParams | None = None) -> list[HilRun]:
    """Run scenarios on one emulated board and write their outputs, as
    :func:`host.hil.runs.run_scenarios` does for the virtual board (same CSV/PNG/GIF; ``params``
    the design, ``plant`` the simulated robot when it differs: ``--plant``)."""
    with EmulatedHil(bundle_dir, firmware=firmware, board=board) as hil:
        return run_all(hil, scenarios, params or load_params(), out=out, compare=compare, gif=gif, plot=plot,
                       progress=progress, on_result=on_result, plant=plant)


def run_all(hil: "EmulatedHil", scenarios: Sequence[Scenario], params: RobotParams, *,
            out: str | Path | None = None, compare: bool = True, gif: bool = True, plot: bool = True,
            progress: Callable[[str, int, int], None] | None = None,
            on_result: Callable[[HilRun], None] | None = None, plant: RobotParams | None = None) -> list[HilRun]:
    """Run scenarios one after another on an open emulated HIL (UART or CAN), with the float
    reference and the outputs as :func:`host.hil.runs.run_scenarios` writes them.  ``params`` is
    the design; ``plant`` (``--plant``) the simulated robot when it differs, the scenario's
    ``[params]`` on top of it, as for the virtual board."""
    from host.hil.runs import write_outputs

    runs: list[HilRun] = []
    for sc in scenarios:
        cb = (lambda k, n, _name=sc.name: progress(_name, k, n)) if progress else None
        run = hil.run(sc, params if plant is None else plant, progress=cb)
        if compare:
            run.reference = float_reference(sc, params, plant=plant, supply_measured=hil.measures_supply)
        if out is not None:
            run.stats["files"] = {k: str(v) for k, v in write_outputs(run, out, gif=gif, plot=plot).items()}
        runs.append(run)
        if on_result is not None:
            on_result(run)
    return runs
