"""HIL Monte Carlo: the firmware in the loop on perturbed robots, one MicroPython process per worker.

Each run ``i`` draws its robot exactly as run ``i`` of the batch robustness sweep does
(:func:`host.studies.sweep.sample_runs`, same seed: the HIL table and the batch table line up
by run index), turns it into the scenario's ``[params]`` overrides and ``[sensors]`` delay, and
closes the scenario through the unchanged firmware on the virtual board (the MicroPython unix
port on a pty, :class:`host.hil.session.HilSession`, lockstep).

A task is ``(HilMcConfig, start, stop)`` like a batch sweep task, so it runs in this process
or on a Dask cluster through :func:`host.studies.sweep.run_tasks` (which keeps the finished
tasks on Ctrl-C).  Each worker process opens one virtual board the first time it runs a task
and keeps it for the next ones (:func:`_session`): one MicroPython interpreter per worker,
closed when the worker process exits.  Run the Dask workers with one thread each
(``dask worker --nthreads 1``): a session is one serial conversation.
"""

from __future__ import annotations

import atexit
import math
import threading
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from sim.params import RobotParams

from .sweep import SweepConfig, Uncertainty, sample_runs

__all__ = ["HilMcConfig", "run_hil_task", "hil_tasks", "close_session", "COLUMNS"]

COLUMNS = ("run", "delay", "M", "m_cam", "m_shaft", "I", "b", "R", "kt", "phi_max", "settle", "xddot_max",
           "passed", "ticks", "worker")
"""Columns of a HIL Monte Carlo table (``settle``: ``inf`` if not settled)."""

_DOTTED = {"M": "cart.M", "m_cam": "pendulum.m_cam", "m_shaft": "pendulum.m_shaft", "I": "pendulum.I",
           "b": "cart.b", "R": "motor.R", "kt": "motor.kt"}


@dataclass(frozen=True)
class HilMcConfig:
    """Everything that defines a HIL Monte Carlo (picklable: shipped to Dask workers).

    Parameters
    ----------
    params : RobotParams
        The design (the firmware's default gains are designed for it) and the centre of the ranges.
    scenario : Scenario
        What every run does (its ``[params]``/``[sensors]`` are replaced by the run's robot;
        its measurement noise stays).
    uncertainty : Uncertainty
        Ranges of the draw (``tilt`` is ignored: the scenario sets the initial state).
    seed : int
        Base seed (run ``i`` draws as run ``i`` of the batch sweep with this seed).
    """

    params: RobotParams
    scenario: Any
    uncertainty: Uncertainty = field(default_factory=Uncertainty)
    seed: int = 0

    def sweep_config(self) -> SweepConfig:
        """The batch sweep whose run ``i`` has the same robot as HIL run ``i``."""
        return SweepConfig(params=self.params, uncertainty=self.uncertainty, seed=self.seed)


def hil_tasks(cfg: HilMcConfig, n: int, chunk: int = 2) -> list[tuple[HilMcConfig, int, int]]:
    """``n`` runs in tasks of ``chunk`` runs."""
    if n < 1 or chunk < 1:
        raise ValueError(f"n and chunk must be >= 1, got {n}, {chunk}")
    return [(cfg, a, min(a + chunk, n)) for a in range(0, n, chunk)]


_LOCK = threading.Lock()
_SESSION: Any = None


def _session() -> Any:
    """This process's virtual board (opened on first use, closed at exit)."""
    global _SESSION
    if _SESSION is None:
        from host.hil.session import HilSession

        _SESSION = HilSession(None, rt_priority=None).open()
        atexit.register(close_session)
    return _SESSION


def close_session() -> None:
    """Close this process's virtual board, if one is open."""
    global _SESSION
    if _SESSION is not None:
        try:
            _SESSION.close()
        finally:
            _SESSION = None


def run_hil_task(cfg: HilMcConfig, start: int, stop: int) -> dict[str, np.ndarray]:
    """Runs ``start .. stop-1`` through the firmware on this process's virtual board; their table."""
    import os

    from sim.metrics import evaluate

    _, drawn = sample_runs(cfg.sweep_config(), start, stop)
    rows: dict[str, list[Any]] = {k: [] for k in COLUMNS}
    with _LOCK:
        sess = _session()
        for j in range(stop - start):
            over = {_DOTTED[k]: float(drawn[k][j]) for k in _DOTTED}
            over["pendulum.L_cm"] = cfg.params.L  # the draw scales both pendulum masses together
            sc = replace(cfg.scenario, param_overrides=over, delay=float(drawn["delay"][j]),
                         name=f"{cfg.scenario.name}_run{int(drawn['run'][j])}")
            run = sess.run(sc, cfg.params)
            summ = evaluate(run.log, sc, cfg.params)
            m = summ.metrics
            for k in ("run", "delay", *_DOTTED):
                rows[k].append(drawn[k][j])
            rows["phi_max"].append(m.peak_phi)
            rows["settle"].append(math.inf if math.isnan(m.settling_time) else m.settling_time)
            rows["xddot_max"].append(m.peak_xddot)
            rows["passed"].append(summ.passed)
            rows["ticks"].append(len(run.log["t"]))
            rows["worker"].append(os.getpid())
    return {k: np.asarray(v) for k, v in rows.items()}
