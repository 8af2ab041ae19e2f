"""A scenario closed through the firmware: :class:`HilRun`, and where the firmware drove the motor."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from firmware import msgtable as T
from sim.params import RobotParams
from sim.scenario import Scenario

__all__ = ["HilRun", "driven_ticks"]

_BALANCING = next(code for code, name, _ in T.STATES if name == "balancing")


def driven_ticks(log: Mapping[str, np.ndarray], n: int | None = None) -> int:
    """Ticks, from the start, during which the firmware drove the motor.

    The firmware drives while it balances; once its supervisor has taken over -- a fault
    latched (tilt, watchdog, implausible sensor...) or the board disarmed, as its answers
    report it (``fw_state``) -- the motor is off, and a float design without a supervisor
    runs on alone.  The stretch ends at the first tick after the firmware started
    balancing whose state is anything else; a log without ``fw_state`` is driven
    throughout.

    Parameters
    ----------
    log : mapping of ndarray
        A run log with ``fw_state`` per tick.
    n : int, optional
        Ticks to consider (default: the whole log).

    Returns
    -------
    int
        Number of leading ticks the firmware drove (``n`` if it never stopped).
    """
    state = log.get("fw_state")
    if n is None:
        n = len(log["phi"])
    if state is None:
        return n
    s = np.asarray(state[:n])
    on = np.nonzero(s == _BALANCING)[0]
    if not on.size:
        return n
    off = np.nonzero(s[on[0]:] != _BALANCING)[0]
    return int(on[0] + off[0]) if off.size else n


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
        included; ``None`` over CAN, whose frames carry no sequence number),
        ``fw_step_us_mean/max`` (from telemetry), time split ``plant_s``/``link_s``; in
        real time also latency and jitter figures and the firmware's ``timing`` message
        (``fw_*``).
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
        """Largest ``|phi_hil - phi_float|`` (rad) against the float reference (nan if none;
        :meth:`phi_error_note` says why).

        Compared only while the firmware drives the motor (:func:`driven_ticks`): once its
        supervisor has taken over (a fault, or the board disarmed), the float design --
        which has no supervisor -- runs on alone.
        The float reference models the tracking row only, so the comparison also stops where
        the firmware's |phi| first reaches the catch-mode threshold (``host.design.catch``);
        a run that starts beyond it has no comparison (nan).
        """
        return self._comparison()[0]

    def phi_error_note(self) -> str | None:
        """Why :meth:`phi_error` is nan, in one line (``None`` when it is a number)."""
        return self._comparison()[1]

    def _comparison(self) -> tuple[float, str | None]:
        if self.reference is None:
            return math.nan, "no float reference (the run was not compared)"
        from host.design.catch import CATCH_DEFAULT

        n = min(len(self.log["phi"]), len(self.reference["phi"]))
        n = driven_ticks(self.log, n)
        big = np.nonzero(np.abs(np.asarray(self.log["phi"][:n], dtype=float)) >= CATCH_DEFAULT.phi_on)[0]
        if big.size:
            if big[0] == 0:
                phi0 = abs(float(self.log["phi"][0]))
                return math.nan, (f"starts at |phi| = {phi0:.2f} rad, beyond the catch-mode threshold "
                                  f"({CATCH_DEFAULT.phi_on:g} rad): the firmware catches with its second force row, "
                                  "the float design models the tracking row only")
            n = int(big[0])
        return (float(np.max(np.abs(self.log["phi"][:n] - self.reference["phi"][:n]))) if n else 0.0), None

    def summary(self, name: str | None = None) -> Any:
        """Metrics and constraint checks (:class:`sim.metrics.RunSummary`)."""
        from sim.metrics import evaluate

        return evaluate(self.log, self.scenario, self.params, name=name or self.name)
