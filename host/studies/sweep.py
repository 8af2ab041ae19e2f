"""Batch sweeps: robustness Monte Carlo, weight tuning and largest recoverable tilt.

A sweep is a list of *tasks* ``(SweepConfig, start, stop)``; each task simulates runs
``start .. stop-1`` of its configuration with :func:`sim.batch.simulate_batch` and returns
a table (dict of equal-length columns).  Everything random about run ``i`` -- its robot,
delay, initial tilt and noise stream -- is drawn from ``SeedSequence(seed, spawn_key=(i,))``,
so a table does not depend on how the runs were split into tasks, nor on where the
tasks ran (:mod:`host.studies.dask_run` runs them on a Dask cluster).

Constraints (the report's, from the robot file): ``|phi| < phi_max`` (0.3 rad), settling
of ``|phi|`` into ``settle_band`` before ``t_settle`` (2.5 s), ``|xddot| <= a_max``
(5 m/s^2); a fallen pendulum fails everything.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np

from host.design.uncertainty import Axis, scaled_values
from sim.batch import METRICS, RunSet, simulate_batch
from sim.params import SCHEMA, RobotParams
from sim.scenario import Expectation, Scenario, dump_scenario
from sim.sensors import NoiseModel, delay_steps

__all__ = [
    "SweepError",
    "SweepInterrupted",
    "Uncertainty",
    "Design",
    "SweepConfig",
    "Task",
    "tasks_for",
    "default_chunk",
    "run_task",
    "run_tasks",
    "concat",
    "robustness",
    "summarise",
    "worst_cases",
    "worst_case_scenarios",
    "runset_from_scenario",
    "design_grid",
    "design_random",
    "tune",
    "pareto_front",
    "tilt",
    "physical_tilt_limit",
    "default_tilt_designs",
    "write_scenarios",
    "sample_runs",
    "checks",
]

_SAMPLED = ("M", "m_cam", "m_shaft", "I", "b", "R", "kt")  # robot-file keys a run varies
_DOTTED = {k.split(".", 1)[1]: k for k in SCHEMA}


class SweepError(ValueError):
    """Bad sweep inputs (sizes, ranges, designs)."""


class SweepInterrupted(KeyboardInterrupt):
    """A sweep stopped by Ctrl-C; carries the tables of the tasks that had finished.

    It is a ``KeyboardInterrupt``, so code that does not look at the partial results still
    stops as on any Ctrl-C.

    Attributes
    ----------
    tables : list of dict
        The finished tasks' tables, in task order (possibly with gaps on Dask: each table's
        ``run`` column says which runs it holds).
    runs_done, runs_total : int
        Runs finished, runs planned.
    """

    def __init__(self, tables: list[dict[str, np.ndarray]], runs_done: int, runs_total: int) -> None:
        super().__init__(f"interrupted after {runs_done} of {runs_total} runs")
        self.tables = tables
        self.runs_done = runs_done
        self.runs_total = runs_total

    @property
    def table(self) -> dict[str, np.ndarray]:
        """The finished runs as one table (empty when none finished)."""
        return concat(self.tables)


@dataclass(frozen=True)
class Uncertainty:
    """Ranges of the Monte Carlo: the sweep's parametrisation of the one uncertainty model
    (:meth:`axes`, :class:`host.design.uncertainty.Axis`; ``--ranges FILE``: :mod:`.ranges`).

    Parameters
    ----------
    mass : float
        Relative half-range of the cart mass and, independently, of the pendulum masses
        (camera and shaft scaled together).
    inertia : float
        Relative half-range of the pendulum inertia about the pivot (on top of the mass).
    friction : (float, float)
        Factor range of the cart friction ``b`` (log-uniform).
    motor : float
        Relative half-range of the motor resistance ``R`` and torque constant ``kt``
        (independently).
    delay : (float, float)
        Measurement delay range (s), rounded to whole control ticks.
    tilt : float
        Initial tilt uniform in ``[-tilt, tilt]`` (rad), released at rest.
    """

    mass: float = 0.10
    inertia: float = 0.10
    friction: tuple[float, float] = (0.5, 2.0)
    motor: float = 0.10
    delay: tuple[float, float] = (0.005, 0.020)
    tilt: float = 0.03

    def __post_init__(self) -> None:
        for k in ("mass", "inertia", "motor"):
            v = getattr(self, k)
            if not 0.0 <= v < 1.0:
                raise SweepError(f"uncertainty {k} must be in [0, 1), got {v!r}")
        lo, hi = self.friction
        if not 0 < lo <= hi:
            raise SweepError(f"friction factors must satisfy 0 < lo <= hi, got {self.friction!r}")
        lo, hi = self.delay
        if not 0 <= lo <= hi <= 0.1:
            raise SweepError(f"delay range must satisfy 0 <= lo <= hi <= 0.1 s, got {self.delay!r}")
        if not 0 <= self.tilt < math.pi / 2:
            raise SweepError(f"tilt must be in [0, pi/2), got {self.tilt!r}")

    def axes(self) -> dict[str, Axis]:
        """The Monte Carlo in the one uncertainty model (:class:`host.design.uncertainty.Axis`).

        In the order of a run's uniforms: cart mass, pendulum masses, inertia (coupled to the
        pendulum masses), friction (log-uniform), resistance, torque constant, delay (s), tilt (rad).
        """
        return {a.key: a for a in (
            Axis.symmetric("cart_mass", 1.0, self.mass),
            Axis.symmetric("pendulum_mass", 1.0, self.mass),
            Axis.symmetric("inertia", 1.0, self.inertia, times="pendulum_mass"),
            Axis.log_uniform("friction", *self.friction),
            Axis.symmetric("resistance", 1.0, self.motor),
            Axis.symmetric("motor_constant", 1.0, self.motor),
            Axis.uniform("delay", *self.delay),
            Axis.symmetric("tilt", 0.0, self.tilt),
        )}

    @classmethod
    def none(cls) -> "Uncertainty":
        """No uncertainty at all (nominal robot, nominal delay chosen by the caller)."""
        return cls(mass=0.0, inertia=0.0, friction=(1.0, 1.0), motor=0.0, delay=(0.0, 0.0), tilt=0.0)


@dataclass(frozen=True)
class Design:
    """A controller design: LQR weights and observer speed (see :mod:`host.design.discrete`).

    Parameters
    ----------
    name : str
        Label in tables and plots.
    Q : 4 floats
        Diagonal of the continuous LQR state weight ``[x, xdot, phi, phidot]``.
    R : float
        Continuous LQR input weight.
    observer : float, optional
        Observer speed factor: the Kalman filter is designed for measurement noise
        ``SIGMA_MEAS / observer`` (> 1 trusts the sensors more: a faster observer); default
        the shipped design's (``host.design.discrete.OBSERVER_DEFAULT``).
    K : 4 floats, optional
        A fixed state-feedback gain instead of LQR (``design="gain"``).
    u_max : float, optional
        Force saturation of the controller (N); default the drive's stall force.
    """

    name: str = "lqr"
    Q: tuple[float, float, float, float] | None = None
    R: float | None = None
    observer: float | None = None
    K: tuple[float, float, float, float] | None = None
    u_max: float | None = None

    def controller(self, params: RobotParams) -> Any:
        """The :class:`host.design.discrete.DiscreteController` of this design for ``params``."""
        from host.design import discrete

        if self.observer is not None and not self.observer > 0:
            raise SweepError(f"observer speed factor must be > 0, got {self.observer!r}")
        if self.K is not None:
            return discrete.controller_ss(params, design="gain", K=self.K, u_max=self.u_max, observer=self.observer)
        return discrete.controller_ss(params, Q=self.Q, R=self.R, u_max=self.u_max, observer=self.observer)

    def as_dict(self) -> dict[str, Any]:
        """Columns describing the design (for tables)."""
        from host.design import discrete

        q = self.Q if self.Q is not None else discrete.Q_DEFAULT
        return {
            "design": self.name,
            "q_x": float(q[0]) if self.K is None else math.nan,
            "q_phi": float(q[2]) if self.K is None else math.nan,
            "r": float(self.R if self.R is not None else discrete.R_DEFAULT) if self.K is None else math.nan,
            "observer": float(discrete.OBSERVER_DEFAULT if self.observer is None else self.observer),
        }


@dataclass(frozen=True)
class SweepConfig:
    """Everything that defines a sweep's runs (picklable: shipped to Dask workers).

    Parameters
    ----------
    params : RobotParams
        Nominal robot (the firmware's parameters and the centre of the ranges).
    design : Design
        Controller design (built from the nominal robot).
    uncertainty : Uncertainty
        Ranges of the Monte Carlo.
    seed : int
        Base seed; run ``i`` uses ``SeedSequence(seed, spawn_key=(i,))``.
    duration : float
        Simulated time per run (s).
    noise : NoiseModel
        Measurement noise (each run its own stream).
    drive : {"motor", "force"}
        Actuator model (see :func:`sim.batch.simulate_batch`).
    settle_band : float
        Settling band on ``|phi|`` (rad), default 0.005.
    tilts : tuple of float, optional
        Tilt mode: run ``i`` is the nominal robot released at rest at ``tilts[i]`` (no
        parameter draw), with the cart acceleration limited to ``a_max``.
    designs : tuple of Design, optional
        Several designs in one sweep (tune, tilt): sweep index ``g`` is run
        ``g % per_design`` of design ``g // per_design`` -- every design sees the same
        runs (common random numbers) and a task simulates all its designs in one batch.
    per_design : int
        Runs per design when ``designs`` is given.
    plant : RobotParams, optional
        The simulated robot when it is not the design's (``--plant``, see
        :func:`sim.params.plant_params`): the centre of the ranges, the nominal delay of the
        tilt mode, the motor and sensors that make the counts.  Default: ``params``.
    engine : str, optional
        :func:`sim.batch.simulate_batch` engine (default: numba when importable).
    """

    params: RobotParams
    design: Design = field(default_factory=Design)
    uncertainty: Uncertainty = field(default_factory=Uncertainty)
    seed: int = 0
    duration: float = 5.0
    noise: NoiseModel = field(default_factory=lambda: NoiseModel("uniform", amplitude=0.001))
    drive: str = "motor"
    settle_band: float = 0.005
    tilts: tuple[float, ...] | None = None
    designs: tuple[Design, ...] = ()
    per_design: int = 0
    plant: RobotParams | None = None
    engine: str | None = None

    def __post_init__(self) -> None:
        if self.designs:
            if self.per_design < 1:
                raise SweepError("per_design must be >= 1 with several designs")
            names = [d.name for d in self.designs]
            if len(set(names)) != len(names):
                raise SweepError(f"design names must be unique, got {names}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise SweepError(f"seed must be a non-negative integer, got {self.seed!r}")
        if not self.duration > 0:
            raise SweepError(f"duration must be > 0, got {self.duration!r}")

    @property
    def size(self) -> int | None:
        """Number of runs fixed by the config (tilt mode, several designs), else ``None``."""
        if self.designs:
            return len(self.designs) * self.per_design
        return None if self.tilts is None else len(self.tilts)


Task = tuple[SweepConfig, int, int]


def _run_seeds(seed: int, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Uniforms (n, 8) for the parameter draw and a 63-bit noise seed per run index."""
    u = np.empty((len(index), 8))
    s = np.empty(len(index), dtype=np.int64)
    for j, i in enumerate(index):
        ss = np.random.SeedSequence(seed, spawn_key=(int(i),))
        p_ss, n_ss = ss.spawn(2)
        u[j] = np.random.default_rng(p_ss).random(8)
        s[j] = int(n_ss.generate_state(1, np.uint64)[0] >> np.uint64(1))
    return u, s


def _true_robot(params: RobotParams, row: Mapping[str, float]) -> RobotParams:
    return params.replace(**row) if row else params


def sample_runs(cfg: SweepConfig, start: int, stop: int) -> tuple[RunSet, dict[str, np.ndarray]]:
    """The runs ``start .. stop-1`` of a sweep and the table of what was drawn.

    Returns
    -------
    (RunSet, dict)
        The batch input, and columns ``run, noise_seed, delay, phi0`` plus the true
        ``M, m_cam, m_shaft, I, b, R, kt`` (robot-file values, replayable as scenario
        ``[params]``).
    """
    if not 0 <= start <= stop or (cfg.size is not None and stop > cfg.size):
        raise SweepError(f"bad run range {start}..{stop} (sweep size {cfg.size})")
    p = cfg.params if cfg.plant is None else cfg.plant
    n = stop - start
    g = np.arange(start, stop, dtype=np.int64)
    index = g % cfg.per_design if cfg.designs else g  # the run of each sweep index
    u, noise_seed = _run_seeds(int(cfg.seed), index)
    rate = p.rate
    if cfg.tilts is not None:
        phi0 = np.asarray(cfg.tilts, dtype=float)[index]
        rows: list[dict[str, float]] = [{} for _ in range(n)]
        dticks = np.full(n, delay_steps(p.delay, rate), dtype=np.int64)
    else:
        ax = cfg.uncertainty.axes()
        f = {k: a.draw(u[:, j]) for j, (k, a) in enumerate(ax.items())}  # column j of the uniforms: axis j
        # the draw is continuous; the simulated delay is the nearest whole tick (the sensors
        # are sampled once per tick) and the table's "delay" column is that simulated delay
        dticks = np.rint(f["delay"] * rate).astype(np.int64)
        phi0 = f["tilt"]
        robot = scaled_values(p, ax, f)
        rows = [{k: float(robot[k][j]) for k in _SAMPLED} for j in range(n)]
    robots = [_true_robot(p, r) for r in rows]
    values = {k: np.array([getattr(r, k) for r in robots]) for k in ("M", "m", "L", "I", "b", "R", "kt")}
    x0 = np.zeros((n, 4))
    x0[:, 2] = phi0
    runs = RunSet(x0=x0, values=values, delay_ticks=dticks, noise_seed=noise_seed)
    table: dict[str, np.ndarray] = {
        "run": index,
        "noise_seed": noise_seed,
        "delay": dticks / rate,
        "phi0": phi0,
    }
    for k in _SAMPLED:
        table[k] = np.array([getattr(r, k) for r in robots])
    if cfg.designs:
        table["design"] = np.array([cfg.designs[int(i)].name for i in g // cfg.per_design])
    return runs, table


def run_task(cfg: SweepConfig, start: int, stop: int) -> dict[str, np.ndarray]:
    """Simulate runs ``start .. stop-1`` of ``cfg``; the table of draws, metrics and checks.

    Pure function of its arguments (what a Dask worker executes).
    """
    p = cfg.params
    runs, table = sample_runs(cfg, start, stop)
    if cfg.designs:
        which = np.arange(start, stop) // cfg.per_design
        used, ctrl_index = np.unique(which, return_inverse=True)
        ctrl: Any = [cfg.designs[int(i)].controller(p) for i in used]
    else:
        ctrl, ctrl_index = cfg.design.controller(p), None
    res = simulate_batch(
        p,
        ctrl,
        runs,
        ctrl_index=ctrl_index,
        duration=cfg.duration,
        noise=cfg.noise,
        drive=cfg.drive,
        settle_band=cfg.settle_band,
        accel_limit=p.a_max if cfg.tilts is not None else None,
        plant=cfg.plant,
        engine=cfg.engine,
    )
    table.update(res.metrics)
    table.update(checks(res.metrics, p))
    return table


def checks(m: Mapping[str, np.ndarray], p: RobotParams) -> dict[str, np.ndarray]:
    """Constraint checks and the worst constraint ratio (> 1 fails) of each run."""
    ok_phi = (m["phi_max"] < p.phi_max) & ~m["fallen"]
    ok_settle = m["settle"] < p.t_settle
    ok_acc = m["xddot_max"] <= p.a_max
    ratio = np.maximum.reduce([m["phi_max"] / p.phi_max, m["settle"] / p.t_settle, m["xddot_max"] / p.a_max])
    ratio = np.where(m["fallen"], np.inf, ratio)
    return {"ok_phi": ok_phi, "ok_settle": ok_settle, "ok_accel": ok_acc, "success": ok_phi & ok_settle & ok_acc,
            "worst_ratio": ratio}


MAX_CHUNK = 5000
"""Most runs in one task by default (memory of the noise block, progress granularity)."""


def default_chunk(n: int, workers: int | None = None) -> int:
    """Runs per task sized to the workers: ``ceil(n / workers)``, at most :data:`MAX_CHUNK`.

    ``workers`` defaults to 1 for a local sweep: there the compiled kernel spreads each task
    over all of numba's threads itself, so one task per process is the right size; on Dask
    give the cluster's worker count (one task per worker).
    """
    w = max(1, int(workers or 1))
    return max(1, min(MAX_CHUNK, -(-int(n) // w)))


def tasks_for(cfg: SweepConfig, n: int, chunk: int | None = None) -> list[Task]:
    """Split ``n`` runs of ``cfg`` into tasks of at most ``chunk`` runs (default
    :func:`default_chunk`)."""
    chunk = default_chunk(n) if chunk is None else chunk
    if n < 1 or chunk < 1:
        raise SweepError(f"need n >= 1 and chunk >= 1, got n={n}, chunk={chunk}")
    return [(cfg, a, min(a + chunk, n)) for a in range(0, n, chunk)]


def concat(tables: Sequence[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Concatenate task tables (same columns) in order."""
    if not tables:
        return {}
    return {k: np.concatenate([t[k] for t in tables]) for k in tables[0]}


def run_tasks(
    tasks: Sequence[Task],
    *,
    scheduler: Any = None,
    progress: Callable[[int, int], None] | None = None,
    fn: Callable[[Any, int, int], dict[str, np.ndarray]] | None = None,
) -> list[dict[str, np.ndarray]]:
    """Run tasks in this process, or on the Dask cluster at ``scheduler``; tables in task order.

    ``progress(runs_done, runs_total)`` is called after each task.  ``fn(cfg, start, stop)``
    runs one task (default :func:`run_task`; the HIL Monte Carlo passes
    :func:`host.studies.hil_mc.run_hil_task`).  ``scheduler`` is an address or a
    ``distributed.Client``.

    Raises
    ------
    SweepInterrupted
        On Ctrl-C (``KeyboardInterrupt``), with the tables of the tasks that had finished.
    """
    total = sum(b - a for _, a, b in tasks)
    finished: dict[int, dict[str, np.ndarray]] = {}
    fn = run_task if fn is None else fn

    def keep(i: int, table: dict[str, np.ndarray]) -> None:
        finished[i] = table

    try:
        if scheduler is not None:
            from .dask_run import run_on_dask

            return run_on_dask(tasks, scheduler, fn, progress=progress, on_result=keep)
        done = 0
        if progress is not None:
            progress(0, total)
        for i, (cfg, a, b) in enumerate(tasks):
            keep(i, fn(cfg, a, b))
            done += b - a
            if progress is not None:
                progress(done, total)
        return [finished[i] for i in range(len(tasks))]
    except KeyboardInterrupt as exc:
        if isinstance(exc, SweepInterrupted):
            raise
        tables = [finished[i] for i in sorted(finished)]
        done = sum(tasks[i][2] - tasks[i][1] for i in finished)
        raise SweepInterrupted(tables, done, total) from None


# ------------------------------------------------------------------ robustness
def robustness(cfg: SweepConfig, n: int, *, chunk: int | None = None, scheduler: str | None = None,
               progress: Callable[[int, int], None] | None = None) -> dict[str, np.ndarray]:
    """Monte Carlo of ``n`` runs; one row per run (see :func:`run_task`)."""
    return concat(run_tasks(tasks_for(cfg, n, chunk), scheduler=scheduler, progress=progress))


def _q(v: np.ndarray, q: float) -> float:
    v = np.asarray(v, dtype=float)
    # a sample value (no interpolation: settling times may be inf)
    return float(np.quantile(v, q, method="inverted_cdf")) if v.size else math.nan


def summarise(table: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Success rates and the distribution (p5, median, p95, max) of every metric."""
    out: dict[str, float] = {"runs": float(len(table["run"]))}
    for k in ("success", "ok_phi", "ok_settle", "ok_accel", "fallen"):
        out[f"{k}_rate"] = float(np.mean(table[k]))
    for k in METRICS:
        if k == "fallen":
            continue
        v = table[k]
        out[f"{k}_p5"], out[f"{k}_p50"], out[f"{k}_p95"] = _q(v, 0.05), _q(v, 0.5), _q(v, 0.95)
        out[f"{k}_max"] = float(np.max(v))
    return out


def worst_cases(table: Mapping[str, np.ndarray], k: int = 5) -> np.ndarray:
    """Row indices of the ``k`` runs with the largest worst-constraint ratio (ties: run order)."""
    order = np.lexsort((table["run"], -np.nan_to_num(table["worst_ratio"], posinf=1e300)))
    return order[: max(0, k)]


def worst_case_scenarios(cfg: SweepConfig, table: Mapping[str, np.ndarray], k: int = 5) -> list[Scenario]:
    """The ``k`` worst runs as replayable :class:`sim.scenario.Scenario` objects.

    Each carries the run's true robot (``[params]``), delay, initial state, noise model and
    noise seed, and in ``[expect]`` what the run showed; :func:`runset_from_scenario`
    (or any simulator reading scenarios) replays it (with the sweep's ``--plant`` file, if
    any, as the plant: the ``[params]`` are the keys that differ from it).
    """
    p = cfg.params if cfg.plant is None else cfg.plant
    out = []
    for rank, i in enumerate(worst_cases(table, k)):
        run = int(table["run"][i])
        res = {
            "phi_max": "pass" if table["ok_phi"][i] else "fail",
            "settle": "pass" if table["ok_settle"][i] else "fail",
            "a_max": "pass" if table["ok_accel"][i] else "fail",
        }
        note = (f"sweep seed {cfg.seed} run {run}, design {cfg.design.name}: phi_max={table['phi_max'][i]:.4g} rad, "
                f"settle={table['settle'][i]:.4g} s, xddot_max={table['xddot_max'][i]:.4g} m/s^2")
        overrides = {_DOTTED[k_]: float(table[k_][i]) for k_ in _SAMPLED if float(table[k_][i]) != float(getattr(p, k_))}
        out.append(Scenario(
            name=f"worst{rank + 1}_seed{cfg.seed}_run{run}",
            duration=float(cfg.duration),
            description=f"robustness sweep worst case #{rank + 1} (worst constraint ratio {table['worst_ratio'][i]:.3g})",
            seed=int(table["noise_seed"][i]),
            x0=(0.0, 0.0, float(table["phi0"][i]), 0.0),
            noise=cfg.noise,
            delay=float(table["delay"][i]),
            param_overrides=overrides,
            expect=Expectation(note=note, **res),
        ))
    return out


def write_scenarios(scenarios: Iterable[Scenario], directory: str) -> list[str]:
    """Write scenarios as ``<name>.toml`` into ``directory``; the paths written."""
    from pathlib import Path

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    paths = []
    for s in scenarios:
        path = d / f"{s.name}.toml"
        path.write_text(dump_scenario(s))
        paths.append(str(path))
    return paths


def runset_from_scenario(scenario: Scenario, params: RobotParams, plant: RobotParams | None = None) -> RunSet:
    """A one-run :class:`RunSet` replaying ``scenario`` (true robot = overrides applied to
    ``plant``, default ``params``; simulate it with the same ``plant=``).

    Raises
    ------
    SweepError
        If the scenario has disturbance forces or a moving reference (the batch simulator
        holds the reference and has no disturbance input).
    """
    if scenario.forces or scenario.reference.kind != "none":
        raise SweepError(f"scenario {scenario.name}: the batch simulator replays no forces and no moving reference")
    true = scenario.apply(params if plant is None else plant)
    values = {k: np.array([getattr(true, k)]) for k in ("M", "m", "L", "I", "b", "g", "V_supply", "R", "kt")}
    return RunSet(
        x0=np.array([scenario.x0]),
        values=values,
        delay_ticks=np.array([delay_steps(true.delay, params.rate)]),
        noise_seed=np.array([scenario.seed]),
        x_ref=np.array([scenario.reference.low]),
    )


# ------------------------------------------------------------------ tuning
def design_grid(q_x: Sequence[float] = (1.0, 5.4, 20.0), q_phi: Sequence[float] = (0.2, 0.8, 4.0),
                r: Sequence[float] = (0.001, 0.01, 0.1), observer: Sequence[float] = (0.3, 1.0, 3.0)) -> list[Design]:
    """Every combination of LQR weights ``Q = diag(q_x, 0, q_phi, 0)``, ``R`` and observer speed."""
    return [Design(name=f"qx{a:g}_qphi{b:g}_r{c:g}_obs{o:g}", Q=(a, 0.0, b, 0.0), R=c, observer=o)
            for a in q_x for b in q_phi for c in r for o in observer]


def design_random(n: int, seed: int = 0) -> list[Design]:
    """``n`` designs with log-uniform weights (q_x 0.1..100, q_phi 0.01..100, R 1e-4..0.1,
    observer 0.1..10)."""
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2**31,)))
    out = []
    for _ in range(n):
        a, b, c, o = (float(10 ** rng.uniform(lo, hi)) for lo, hi in ((-1, 2), (-2, 2), (-4, -1), (-1, 1)))
        out.append(Design(name=f"qx{a:.3g}_qphi{b:.3g}_r{c:.3g}_obs{o:.3g}", Q=(a, 0.0, b, 0.0), R=c, observer=o))
    return out


def tune(cfg: SweepConfig, designs: Sequence[Design], n: int, *, chunk: int | None = None, scheduler: str | None = None,
         progress: Callable[[int, int], None] | None = None) -> tuple[list[dict[str, Any]], dict[str, np.ndarray]]:
    """Score every design by the same robustness sweep (same seeds: common random numbers).

    Returns
    -------
    (rows, table)
        One summary row per design (design columns, ``success_rate``, medians and p95s,
        ``pareto`` flag) and the per-run table of every design (``design`` column).
        Designs the design code rejects get a row with ``error`` and no runs.
    """
    rows: list[dict[str, Any]] = []
    valid: list[Design] = []
    for d in designs:
        try:
            d.controller(cfg.params)
        except ValueError as exc:
            rows.append({**d.as_dict(), "error": str(exc)})
            continue
        valid.append(d)
    if not valid:
        raise SweepError("no valid design to tune")
    multi = replace(cfg, designs=tuple(valid), per_design=n)
    table = concat(run_tasks(tasks_for(multi, len(valid) * n, chunk), scheduler=scheduler, progress=progress))
    for d in valid:
        sel = table["design"] == d.name
        s = summarise({k: v[sel] for k, v in table.items()})
        rows.append({
            **d.as_dict(),
            "success_rate": s["success_rate"],
            "settle_p50": s["settle_p50"],
            "settle_p95": s["settle_p95"],
            "force_max_p50": s["force_max_p50"],
            "force_max_p95": s["force_max_p95"],
            "phi_rms_p50": s["phi_rms_p50"],
            "xddot_max_p95": s["xddot_max_p95"],
            "error": "",
        })
    scored = [r for r in rows if not r["error"]]
    front = pareto_front([(r["settle_p50"], r["force_max_p50"], r["phi_rms_p50"]) for r in scored])
    for i, r in enumerate(scored):
        r["pareto"] = i in front
    for r in rows:
        r.setdefault("pareto", False)
    rows.sort(key=lambda r: (bool(r["error"]), -r.get("success_rate", 0.0), r.get("settle_p50", math.inf)))
    return rows, table


def pareto_front(points: Sequence[Sequence[float]]) -> set[int]:
    """Indices of the non-dominated points (every objective minimised)."""
    P = np.asarray(points, dtype=float)
    keep = set()
    for i in range(len(P)):
        dominated = np.any(np.all(P <= P[i], axis=1) & np.any(P < P[i], axis=1))
        if not dominated:
            keep.add(i)
    return keep


# ------------------------------------------------------------------ tilt
def default_tilt_designs(params: RobotParams) -> list[Design]:
    """The shipped design (with its own force clamp), the report's LQR and pole placement, and
    softer versions of the report's LQR (larger ``R``)."""
    from host.design.controllers import place_gain
    from host.design.discrete import Q_REPORT, R_REPORT, force_clamp

    K = tuple(float(v) for v in place_gain(params))
    return [Design("lqr_default", u_max=force_clamp(params)), Design("lqr_report", Q=Q_REPORT, R=R_REPORT),
            Design("lqr_R0.01", Q=Q_REPORT, R=0.01), Design("lqr_R0.1", Q=Q_REPORT, R=0.1),
            Design("lqr_R1", Q=Q_REPORT, R=1.0), Design("place_report", K=K)]  # type: ignore[arg-type]


def physical_tilt_limit(params: RobotParams) -> float:
    """Largest tilt a pendulum at rest can be recovered from with ``|xddot| <= a_max``:
    ``atan(a_max / g)`` (the pivot must out-accelerate ``g tan(phi)``)."""
    return math.atan(params.a_max / params.g)


def tilt(params: RobotParams, designs: Sequence[Design], *, step: float = 0.005, hi: float | None = None,
         duration: float = 5.0, noise: NoiseModel | None = None, drive: str = "motor", seed: int = 0,
         chunk: int | None = None, scheduler: str | None = None, progress: Callable[[int, int], None] | None = None,
         plant: RobotParams | None = None) -> tuple[list[dict[str, Any]], dict[str, np.ndarray]]:
    """Largest initial tilt each design recovers from with the cart acceleration limited to ``a_max``.

    The drive is limited twice: the controller saturates its force at ``(M + m) a_max``
    (unless the design sets ``u_max``), and the plant's cart acceleration is clipped to
    ``a_max`` (:func:`sim.batch.simulate_batch` ``accel_limit``).
    Every design is released at rest from tilts ``0, step, 2 step, ... hi`` (nominal
    robot and delay); a run *recovers* if the pendulum does not fall and ``|phi|``
    settles into the band before the end.  The recoverable tilt is the largest grid tilt
    below which every tilt recovers.

    Returns
    -------
    (rows, table)
        Per design: ``tilt_max`` (rad and deg), ``tilt_max_track`` (also keeping
        ``|x| <= track``), the physical limit ``atan(a_max/g)``; and the per-run table.
    """
    lim = physical_tilt_limit(params)
    hi = min(1.4, 1.3 * lim) if hi is None else hi
    if not (step > 0 and hi > 0):
        raise SweepError("tilt step and upper end must be > 0")
    tilts = tuple(float(v) for v in np.arange(0.0, hi + step / 2, step))
    noise = NoiseModel() if noise is None else noise
    u_lim = (params.M + params.m) * params.a_max
    designs = [d if d.u_max is not None else replace(d, u_max=u_lim) for d in designs]
    cfg = SweepConfig(params=params, uncertainty=Uncertainty.none(), seed=seed, duration=duration, noise=noise,
                      drive=drive, tilts=tilts, designs=tuple(designs), per_design=len(tilts), plant=plant)
    t = concat(run_tasks(tasks_for(cfg, len(designs) * len(tilts), chunk), scheduler=scheduler, progress=progress))
    rec = ~t["fallen"] & np.isfinite(t["settle"])
    t["recovered"] = rec
    rows = []
    for d in designs:
        sel = t["design"] == d.name
        rows.append({
            "design": d.name,
            "tilt_max": _contiguous(t["phi0"][sel], rec[sel]),
            "tilt_max_track": _contiguous(t["phi0"][sel], (rec & (t["x_max"] <= params.track))[sel]),
            "physical_limit": lim,
        })
    for r in rows:
        for k in ("tilt_max", "tilt_max_track", "physical_limit"):
            r[k + "_deg"] = math.degrees(r[k])
    return rows, t


def _contiguous(tilts: np.ndarray, ok: np.ndarray) -> float:
    best = 0.0
    for a, good in zip(tilts, ok):
        if not good:
            break
        best = float(a)
    return best
