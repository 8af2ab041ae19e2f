"""The robot of ``upright commission --port``: a board on a serial port (a real robot, or the virtual robot).

:class:`PortRobot` offers what :mod:`host.operate.commission` asks of a robot through the board
tools themselves -- :class:`host.operate.board.Board` (identity, raw sensors, gain upload and save),
:func:`host.operate.calibrate.run_calibration` (the guided calibration), :func:`host.operate.excite.run_excite`
(the firmware's PRBS, recorded; a balancing run is stopped as soon as the recorded tilt leaves
the bound) and :class:`host.operate.record.Recorder` (the verification step, from telemetry).
The person's steps (hold upright, take the pendulum off, put it back) are done by the virtual
robot's hands (``upright emulate rp2040 --pty``; :func:`host.operate.calibrate.robot_hands`) or
asked on the terminal.

Time is the board's: the excitation runs are counted in its ticks (``run_excite``'s
``board_seconds``), the verification in its telemetry rows, and every wait and request attempt
is scaled by its clock (:meth:`host.operate.board.Board.measure_speed`), so the virtual robot at
0.05-0.3x real time records the same logs as a real robot, only later; the host heartbeat keeps to
the board's clock too (a slow board flooded with wall-time heartbeats latched its watchdog).

The host cannot push a real cart with 0.2 N: :attr:`PortRobot.can_push` is false, and the
commissioning verifies the 20 cm step only on a board (the push is verified in lockstep HIL).
"""

from __future__ import annotations

import csv
import math
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from host.link import messages as M
from host.operate.board import Board, BoardError, wait_state
from host.operate.commission import CART_DIV, drive_params
from sim.params import RobotParams

__all__ = ["PortRobot"]


class _Stop(BoardError):
    """The recorded tilt left the bound: the excitation is stopped."""


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    head = rows[0]
    out: dict[str, list[float]] = {h: [] for h in head}
    for r in rows[1:]:
        for h, v in zip(head, r):
            try:
                out[h].append(float(v) if v not in ("", "None") else math.nan)
            except ValueError:
                out[h].append(math.nan)
    return {h: np.asarray(v) for h, v in out.items()}


class PortRobot:
    """A board on ``port`` operated by the board tools (module docstring).

    Parameters
    ----------
    port : str
    baudrate : int, optional
    timeout : float, optional
        Seconds per request attempt (default: 0.3 s scaled by the board's measured speed,
        :meth:`host.operate.board.Board.measure_speed`).
    hands : str
        ``auto`` (the virtual robot's hands if one listens on the port), ``person``, or a socket path.
    say : callable
        Prompts and progress.
    ask : callable, optional
        ``ask(prompt) -> str`` for a person's steps (default: ``input``).
    """

    kind = "port"
    can_push = False

    def __init__(self, port: str, *, baudrate: int | None = None, hands: str = "auto", timeout: float | None = None,
                 say: Callable[[str], None] = print, ask: Callable[..., str] | None = None) -> None:
        self.port = port
        self.baudrate = baudrate
        self.timeout = timeout
        self.hands_choice = hands
        self.say = say
        self.ask = ask or (lambda prompt, idle=None: input(prompt + " [Enter] "))
        self.board: Board | None = None
        self.hands: Any = None
        self.fw_params: RobotParams | None = None
        self.workdir = Path(".")
        self.speed = 1.0

    def open(self) -> "PortRobot":
        """Open the board (identity checked) and find the hands."""
        from host.operate.calibrate import robot_hands

        # timeout None: the request time scaled by the board's measured speed (Board.measure_speed)
        self.board = Board.open(self.port, baudrate=self.baudrate, timeout=self.timeout)
        self.hands = robot_hands(self.hands_choice, self.port)
        self.speed = self.board.speed
        if self.speed < 0.9:
            self.say(f"  the board runs at {self.speed:.2f}x real time (emulated): {self.board.timeout:.1f} s per "
                     "request attempt, the runs counted in its own ticks")
        return self

    def close(self) -> None:
        """Disarm if armed here, close the link and the hands."""
        if self.hands is not None:
            self.hands.close()
        if self.board is not None:
            self.board.close(disarm=True)

    def __enter__(self) -> "PortRobot":
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _b(self) -> Board:
        assert self.board is not None, "open() first"
        return self.board

    def _person(self, action: str, prompt: str, **kw: Any) -> None:
        if self.hands is not None:
            self.hands.do(action, **kw)
        else:
            self.ask(prompt)

    # ---- what commissioning asks
    def identity(self) -> dict[str, Any]:
        """The board's identity (the message-table hash checked)."""
        return self._b().identify(check=True)

    def sensors(self, seconds: float = 0.5) -> dict[str, Any]:
        """Raw readings with the pendulum held upright and the cart still."""
        from host.operate.calibrate import sample

        b = self._b()
        if b.state(fresh=True)["state_name"] in ("armed", "balancing"):
            raise BoardError(f"{self.port}: the board is armed: disarm before commissioning")
        self._person("hold", "hold the pendulum upright and the cart still", phi=0.0, cart="still")
        s = sample(b, seconds)
        full = 2**12
        spread = 3.0 * s["adc_std"]
        return {"adc_mean": s["adc_mean"], "adc_min": int(s["adc_mean"] - spread), "adc_max": int(s["adc_mean"] + spread),
                "enc_span": abs(int(s["enc_last"]) - int(s["enc_first"])), "adc_full": full}

    def calibrate(self, p: RobotParams, out: Path) -> RobotParams:
        """The guided calibration (:func:`host.operate.calibrate.run_calibration`) from robot file ``p``."""
        from host.operate.calibrate import run_calibration
        from host.studies.identify import robot_toml
        from sim.params import load_params

        self.workdir = out.parent
        src = out.with_name("robot_start.toml")
        src.write_text(robot_toml(p, "upright commission: the robot file it started from"))
        run_calibration(self._b(), self.ask, self.say, robot_in=src, robot_out=out, robot=self.hands)
        return load_params(out)

    def upload(self, blob: bytes, fw_params: RobotParams, save: bool = True) -> None:
        """Upload the table (CRC read back) and the firmware parameters that go with it
        (:func:`host.operate.commission.drive_params`), and save them on the board."""
        b = self._b()
        b.upload_gains(blob)
        for name, value in drive_params(fw_params).items():
            b.param_set(name, value)
        if save:
            b.save()
        self.fw_params = fw_params

    def excite(self, mode: int, amp_n: float, *, seconds: float, div: int | None = None, coast_s: float = 3.0,
               phi_stop: float = math.inf) -> Any:
        """One excitation run recorded (:func:`host.operate.excite.run_excite`); see the lockstep robot's.

        ``div`` (control ticks per PRBS bit): default :data:`CART_DIV` for the cart-only run, else 4.
        """
        if div is None:
            div = CART_DIV if mode == 2 else 4
        from host.operate.commission_lockstep import ExciteRun
        from host.operate.excite import run_excite

        b = self._b()
        path = self.workdir / f"excite_{'cart' if mode == 2 else 'bal'}_{time.monotonic_ns()}.csv"
        if mode == 2:
            self._person("pendulum", "take the pendulum off (or lock it upright)", on=False)
        else:
            self._person("hold", "hold the pendulum upright; it is let go when the motor drives", phi=0.0,
                         cart="still", until="driving")

        def progress(el: float, total: float, rec: Any) -> None:
            lo, hi = rec.span["phi"]
            if lo <= hi and max(abs(lo), abs(hi)) > phi_stop:
                raise _Stop("tilt beyond the bound")

        stopped = False
        try:
            # durations in the board's own ticks: the same log whatever the board's speed
            run_excite(b, path, seconds=seconds, board_seconds=seconds, amplitude_n=amp_n, div=div,
                       cart_only=(mode == 2), coast_s=coast_s, board_coast_s=coast_s,
                       progress=progress if mode == 1 else None)
        except BoardError as exc:
            if not isinstance(exc.__cause__, _Stop):
                raise
            stopped = True
        finally:
            if mode == 2:
                self._person("pendulum", "put the pendulum back", on=True)
        cols = _read_csv(path)
        n = len(cols["x"])
        cols["t"] = np.arange(n) / float(self.fw_params.rate if self.fw_params else 500.0)
        exc_on = cols.get("excite", np.zeros(n)) > 0
        fell = mode == 1 and bool(np.any(np.abs(cols["phi"][exc_on]) >= 0.3))
        flags = int(np.bitwise_or.reduce(np.nan_to_num(cols["faults"][exc_on]).astype(np.int64))) if exc_on.any() else 0
        if flags and not fell:
            from host.operate.board import fault_names

            raise BoardError(f"{self.port}: the board latched {', '.join(fault_names(flags))} during the "
                             f"{'cart-only' if mode == 2 else 'balancing'} excitation at {amp_n:.2f} N (log {path})")
        return ExciteRun(cols, np.full((n, 4), math.nan), n - 1 if stopped else None, fell)

    def run_scenario(self, scenario: Any) -> dict[str, np.ndarray]:
        """The 20 cm step on the robot: balance 1 s, step the reference, record its telemetry for the
        scenario's duration in control ticks (the board's time, not the host's)."""
        from host.operate.record import Recorder

        b = self._b()
        p = self.fw_params
        assert p is not None, "upload a table first"
        if scenario.forces:
            raise BoardError("the host cannot push the cart: the push is verified in lockstep HIL")
        old = b.param_get("telem_div")
        b.param_set("telem_div", 1)
        path = self.workdir / f"verify_raw_{scenario.name}.csv"
        self._person("hold", "hold the pendulum upright; it is let go when the motor drives", phi=0.0, cart="still",
                     until="driving")
        rec = Recorder(b, path)
        try:
            if b.state(fresh=True)["faults"]:
                b.clear_faults()
            b.set_reference(0.0)
            b.arm()
            if wait_state(b, ("balancing",), b.wall(5.0)) != "balancing":
                raise BoardError(f"{self.port}: the board did not start balancing")
            n_ticks = int(round(scenario.duration * float(p.rate)))
            t_ref = scenario.reference
            # what the link queued while the arm was awaited (telemetry and heartbeats of before it,
            # labelled disarmed) is recorded first: the scenario starts after the first periodic
            # heartbeat that says balancing (the stream is in order: every row after it is later)
            t_end = time.monotonic() + b.wall(2.0)
            seen = False
            while not seen:
                if time.monotonic() > t_end:
                    raise BoardError(f"{self.port}: no heartbeat says balancing within 2 s of the board's time")
                b.keepalive()
                seen = any(m.NAME == "heartbeat" and sq is not None and M.STATES.get(m.state) == "balancing"
                           for m, sq, _ in b.poll(0.02))
            n0 = rec.rows  # the scenario's first row
            ref = 0.0
            while rec.rows - n0 < n_ticks:
                # the scenario's reference on the board's clock (its ticks as recorded)
                r = float(t_ref.at((rec.rows - n0) / float(p.rate)))
                if r != ref:
                    b.set_reference(r)
                    ref = r
                b.keepalive()
                b.poll(0.02)
        finally:
            b.safe_disarm()
            rec.close()
            b.param_set("telem_div", old)
        # the scenario's rows only: those recorded before (disarmed, arming: labelled with the
        # heartbeat of before the arm) and after it (the disarm) are no part of it -- kept, they read
        # as a fall (state != balancing) in the verdict
        cols = {k: v[n0:n0 + n_ticks] for k, v in _read_csv(path).items()}
        n = len(cols["x"])
        return {"t": np.arange(n) / float(p.rate), "x": cols["x"] - cols["x"][0], "phi": cols["phi"],
                "x_ref": cols["ref"] - cols["x"][0], "duty": cols["duty"], "state": cols["state"], "faults": cols["faults"]}
