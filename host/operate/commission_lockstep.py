"""The robot of ``upright commission`` in lockstep HIL: the firmware on the unix port, the plant on the host.

:class:`LockstepRobot` offers what :mod:`host.operate.commission` asks of a robot -- identity,
sensor readings, gain uploads, the firmware's own excitation (EXCITE) recorded tick by tick
as ``upright board excite`` records it, and the report's step and push -- on the unchanged
firmware (:class:`host.hil.session.HilSession`, its HIL main in lockstep) closed around a
simulated robot through :class:`host.hil.lockstep.Lockstep` (the one lockstep loop).  The plant
is :class:`host.hil.virtual_robot.RobotPlant` (the virtual robot's, with Coulomb and static
friction, backlash, deadband, minimum duty and a nonlinear pot from the robot file), so the
cart-only run takes the pendulum off and coasts with the bridge disabled exactly as there.

What the host would read from telemetry is made from what the board read: ``x`` and ``phi``
from the sensor counts sent each tick with the firmware's calibration (the robot file its
table was designed for), the duty from its answer.  The true state is kept beside it
(:attr:`ExciteRun.truth`) for the bench.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from firmware import supervisor
from host.hil.lockstep import Lockstep
from host.hil.accounting import Sink
from host.hil.session import HilSession
from host.hil.virtual_robot import RobotPlant
from host.link import messages as M
from host.operate.board import BoardError
from host.operate.commission import drive_params
from sim import sensors as ssens
from sim.params import RobotParams

__all__ = ["LockstepRobot", "ExciteRun", "sensor_xphi"]

_EXCITE = M.BY_NAME["excite"]
_DISARM = M.BY_NAME["disarm"]
_START_S = 0.5  # s of balancing before the excitation starts


def sensor_xphi(adc: np.ndarray, enc: np.ndarray, fw: RobotParams) -> tuple[np.ndarray, np.ndarray]:
    """``x`` (m, from the first reading) and ``phi`` (rad) as the firmware converts the counts
    with its calibration ``fw``, in the telemetry's 1e-4 steps."""
    d = ssens.encoder_delta(np.asarray(enc)[1:], np.asarray(enc)[:-1])
    x = np.concatenate([[0.0], np.cumsum(d)]) / ssens.enc_counts_per_m(fw)
    phi = ssens.adc_to_phi(adc, fw)
    return np.round(x, 4), np.round(phi, 4)


@dataclass
class ExciteRun:
    """One recorded run: the log columns (``t, x, phi, duty, state, faults, excite``) and the plant's truth."""

    columns: dict[str, np.ndarray]
    truth: np.ndarray  # (n, 4) true x, xdot, phi, phidot
    stopped_at: int | None  # tick where the excitation was stopped for |phi| (None: ran to the end)
    fell: bool


class _Plant(RobotPlant):
    # RobotPlant for one lockstep run: no hands, a finite run, the bridge enabled only while balancing
    def __init__(self, params: RobotParams, n_ticks: int, *, pendulum: bool, seed: int) -> None:
        super().__init__(params, seed=seed)
        self.hand = None
        self.pendulum_on = bool(pendulum)
        self.n_ticks = int(n_ticks)
        self.driven = True
        self.off_from = self.n_ticks  # the tick from which the host has disarmed (the bridge off)
        self.truth = np.zeros((self.n_ticks, 4))

    def step(self, duty: int, *, u_cmd: float = math.nan, u_sat: float = math.nan, driven: bool = True) -> None:
        if self.tick < self.n_ticks:
            self.truth[self.tick] = self._x
        # the bridge disabled (no back-EMF braking) only for the cart alone: RobotPlant's
        # pendulum-on path divides by the back-EMF constant it zeroes when a realism key is set
        # (sim/plantsim.py _integrate_real; reported) -- there a disabled bridge is duty 0
        off = not (self.driven and driven) or self.tick >= self.off_from
        super().step(0 if off else duty, driven=not (off and not self.pendulum_on))


class LockstepRobot:
    """A simulated robot with the firmware in the loop (module docstring).

    Parameters
    ----------
    plant : RobotParams
        The robot that is simulated (unknown to the commissioning).
    seed : int
        Noise seed of the plant runs.
    """

    kind = "lockstep"

    def __init__(self, plant: RobotParams, *, seed: int = 0) -> None:
        self.plant = plant
        self.seed = int(seed)
        self.session = HilSession(timeout=5.0, rt_priority=None)
        self.blob: bytes | None = None
        self.fw_params: RobotParams | None = None  # the robot file the uploaded table was designed for
        self.fw_set: dict[str, int] = {}  # the firmware parameters that go with the table (drive_params)
        self.hands = None

    # ---- lifecycle
    def open(self) -> "LockstepRobot":
        """Start the firmware (unix port on a pty)."""
        self.session.open()
        return self

    def close(self) -> None:
        """Stop it."""
        self.session.close()

    def __enter__(self) -> "LockstepRobot":
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- what commissioning asks
    def identity(self) -> dict[str, Any]:
        """The board's VERSION answer (identity checked by the link)."""
        v = self.session.link.identify()  # type: ignore[union-attr]
        return {f.name: getattr(v, f.name) for f in v.FIELDS} if hasattr(v, "FIELDS") else {"version": str(v)}

    def sensors(self, seconds: float = 0.5) -> dict[str, Any]:
        """Readings with the pendulum held upright at rest (ADC, encoder), as the calibration's first step."""
        sim = _Plant(self.plant, int(round(seconds * self.plant.rate)), pendulum=True, seed=self.seed)
        adc = []
        enc = []
        for _ in range(sim.n_ticks):
            a, e = sim.read()
            adc.append(a)
            enc.append(e)
            sim.step(0)
        adc_a = np.asarray(adc)
        return {"adc_mean": float(adc_a.mean()), "adc_min": int(adc_a.min()), "adc_max": int(adc_a.max()),
                "enc_span": int(np.ptp(enc)), "adc_full": 2 ** int(self.plant.adc_bits)}

    def upload(self, blob: bytes, fw_params: RobotParams, save: bool = True) -> None:
        """Run with this gain table from now on (uploaded, CRC read back, before each run)."""
        self.blob = bytes(blob)
        self.fw_params = fw_params
        self.fw_set = drive_params(fw_params)
        self.session.use_gains(self.blob, "commission")

    def excite(self, mode: int, amp_n: float, *, seconds: float, div: int = 4, coast_s: float = 3.0,
               phi_stop: float = math.inf) -> ExciteRun:
        """Balance (or, ``mode`` 2, the cart alone: pendulum off), run EXCITE(mode, amp_n, div) for
        ``seconds``; mode 2 then disarms and records ``coast_s`` of coast-down; mode 1 stops the
        excitation as soon as the measured ``|phi|`` exceeds ``phi_stop`` and keeps balancing."""
        assert self.fw_params is not None, "upload a table first"
        rate = float(self.plant.rate)
        n0 = int(round(_START_S * rate))
        n1 = n0 + int(round(seconds * rate))
        n = n1 + (int(round(coast_s * rate)) if mode == 2 else 0)
        sim = _Plant(self.plant, n, pendulum=(mode != 2), seed=self.seed)
        if mode == 2:
            sim.off_from = n1  # the DISARM goes out before tick n1's frame: that tick's answer is disarmed
        s = self.session
        link = s.link
        sink = Sink(link)
        s.prepare(sim, sink, fw_params=self.fw_set)
        fw = self.fw_params
        cpr = float(ssens.adc_counts_per_rad(fw))
        state = {"stop": None, "sent_stop": False}
        exc = np.zeros(n)

        def on_tick(k: int) -> None:
            if k == n0:
                link.send(_EXCITE(mode=int(mode), div=int(div), amp_mn=int(round(amp_n * 1000))))  # type: ignore[union-attr]
            elif k == n1 and mode == 2:
                link.send(_DISARM())  # type: ignore[union-attr]
            elif state["stop"] is not None and not state["sent_stop"]:
                link.send(_EXCITE(mode=0, div=1, amp_mn=0))  # type: ignore[union-attr]
                state["sent_stop"] = True

        def after_tick(k: int, m: Any) -> None:
            sim.driven = m is not None and m.state == supervisor.BALANCING
            if n0 < k and state["stop"] is None:
                exc[k] = mode
                if mode == 1 and abs(float(loop.adc_sent[k]) - fw.pot_offset) / cpr > phi_stop:
                    state["stop"] = k
            if mode == 2 and k >= n1:
                exc[k] = mode

        loop = Lockstep(s, sim, sink=sink, depth=0, on_tick=on_tick, after_tick=after_tick)
        loop.run()
        s.finish()
        refused = [m for _, m in sink.replies if m.NAME == "nack" and m.msg_id == _EXCITE.ID]
        if refused:
            # as the board tools do (upright board excite exits 1): never a log of an excitation that did not run
            raise BoardError(f"the board refused EXCITE(mode {mode}, {amp_n:g} N, div {div}): "
                             f"{M.REASON_NAMES.get(refused[0].reason, refused[0].reason)}")
        x, phi = sensor_xphi(loop.adc_sent, loop.enc_sent, fw)
        cols = {"t": np.arange(n) / rate, "x": x, "phi": phi, "duty": loop.duty_fw.astype(float),
                "state": loop.fw_state.astype(float), "faults": loop.fw_faults.astype(float), "excite": exc,
                "seq": (np.arange(n) % 256).astype(float)}
        fell = mode != 2 and bool(np.max(np.abs(sim.truth[:, 2])) >= float(self.plant.phi_max))
        return ExciteRun(cols, sim.truth, state["stop"], fell)

    def run_scenario(self, scenario: Any) -> dict[str, np.ndarray]:
        """The scenario (the report's step or push) with the uploaded table; the log as the host
        reads it (``t, x, phi, x_ref, duty, state, faults``) plus the truth (``true_*``)."""
        assert self.fw_params is not None, "upload a table first"
        r = self.session.run_lockstep(scenario, self.plant, pipeline=0, seed=self.seed, fw_params=self.fw_set)
        lg = r.log
        x, phi = sensor_xphi(lg["adc"], lg["enc"], self.fw_params)
        return {"t": lg["t"], "x": x, "phi": phi, "x_ref": lg["x_ref"], "duty": lg["duty"].astype(float),
                "state": lg["fw_state"].astype(float), "faults": lg["fw_faults"].astype(float),
                "true_x": lg["x"], "true_phi": lg["phi"], "true_xddot": lg["xddot"], "force": lg["force"]}
