"""Robust design: the worst case of a design over an uncertainty set, and a search for the best.

The **uncertainty set** (:class:`UncertaintySet`, ``sim/uncertainty.toml`` by default) is a box of
factors on the design model's values -- pivot inertia, cart mass, pendulum mass, friction,
supply voltage, motor constant -- and a range of measurement delays.  A design is scored at
every vertex of the box and at seeded random points inside it (:meth:`UncertaintySet.points`).

A **candidate** (:class:`Candidate`) is what the firmware's gain table carries: LQR weights
``Q`` (diagonal) and ``R``, the estimator (the Kalman filter's measurement noise divided by an
``observer`` speed factor) and the force clamp (``a_cmd``: the cart acceleration the clamp
allows from upright, :func:`host.design.discrete.force_clamp`) and, for the margin design of
:mod:`host.design.margin`, the integral gain ``ki`` (one type for both).  The design model is always
the nominal robot: the firmware does not know where in the box the real robot is.

**Scoring** (:func:`evaluate`) uses the report's scenarios on the nonlinear plant with the
sensors' quantisation, the true motor (supply, back-EMF) and the delayed, discrete loop:

* ``step`` -- the 20 cm cart step held 5 s (``ref_step_20cm``): both edges, each from rest,
  i.e. a +20 cm and a -20 cm step over 5 s each;
* ``square`` -- the 20 cm square wave, each level held 2.2 s (``square_wave_20cm_2p2s``): its
  edges from rest, +-20 cm, each to settle within its 2.2 s level;
* ``tilt`` -- released at rest with 0.1 rad (``tilt_0p1``), 5 s;
* ``push`` -- 0.2 N on the cart for 5 s (``push_0p2N_5s``, 8 s);
* ``kick`` -- the 1 N s kick on the cart at rest (``impulse_kick``: the kick comes 0.5 s into a
  5 s run, so 4.5 s after it), started as the velocity jump the kick gives that robot (as
  :class:`sim.plantsim.PlantSim` applies a Dirac impulse): tilt and settling only -- its
  acceleration is not a constraint, since the drive's back-EMF brakes the kicked cart at
  ~100 m/s^2 whatever the controller does (the scenario's ``[expect]``).

``step``, ``square``, ``tilt`` and ``kick`` run in the batch simulator (:func:`sim.batch.simulate_batch`,
traces recorded), one run per point and edge; the metrics are the scenario metrics of
:func:`sim.metrics.compute_metrics` on those traces (settling of phi and, with a reference,
of x) with the batch's own peak |xddot|.  The batch cannot apply a force profile, so ``push``
runs in the scenario simulator (:func:`sim.plantsim.run_scenario_float`) at the nominal point
and the ``push_points`` points worst for the batch scenarios (during the search, at the
nominal point only: :attr:`Evaluation.nominal_ok`).

Constraints (the report's, from the robot file): ``|phi| < phi_max`` (0.3 rad), ``|xddot| <=
a_max`` (5 m/s^2), settling ``<= t_settle`` (2.5 s; the square wave's level is 2.2 s, so
there it must settle within the level).  :func:`search` (in :mod:`host.design.robust_search`)
maximises the worst case.

The controller is the float :class:`~host.design.discrete.DiscreteController` whose tables the
firmware runs in fixed point (the export's quantisation error is below one output LSB, and
HIL agrees with the float loop within two ADC counts: ``docs/parameters.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Mapping, Sequence

import numpy as np

from sim.params import RobotParams

from .integral import IntegralController
from .uncertainty import (FACTORS, UNCERTAINTY_FILE, Point, UncertaintyError, UncertaintySet, load_uncertainty,
                          uncertainty_from_dict)

__all__ = [
    "UNCERTAINTY_FILE",
    "FACTORS",
    "SCENARIOS",
    "CONSTRAINTS",
    "UncertaintyError",
    "UncertaintySet",
    "Point",
    "load_uncertainty",
    "uncertainty_from_dict",
    "Candidate",
    "shipped",
    "Evaluation",
    "evaluate",
    "worst_rows",
    "corner_scenario",
    "simulate_corner",
    "plant_toml",
    "MeasuredStart",
]

SCENARIOS = ("step", "square", "push", "kick", "tilt")
FORCE_SCENARIOS = {"push": "push_0p2N_5s"}
"""The scenarios with a force profile on the cart: run in the scenario simulator, not the batch."""
FORCE_LSB_MAX = 40.0
"""Largest worst-case error (output LSB, 2**-9 N) of the fixed-point force row a shipped design may
have: a design with larger gains gets a coarser row (the accumulator must fit 2**30), and its
command drifts from the float design the evaluation scores (the previous default: 34 LSB)."""
KICK = 1.0  # N s, the report's kick (sim/scenarios/impulse_kick.toml)
KICK_S = 4.5  # s, from the kick to the end of that scenario
CONSTRAINTS = ("phi_max", "a_max", "settle")
STEP = 0.2  # m, the report's cart step and square-wave amplitude
SQUARE_LEVEL = 2.2  # s, each level of the report's square wave
TILT = 0.1  # rad
RUN_S = 5.0  # s, batch runs (the step's hold)
UNSETTLED = 5.0  # ratio given to a run that never settles; every ratio is capped there (a fall is a fall)


@dataclass(frozen=True)
class Candidate:
    """A design: LQR weights, estimator speed and force clamp (what a gain table carries).

    Parameters
    ----------
    name : str
    Q : 4 floats
        Diagonal of the continuous LQR state weight ``[x, xdot, phi, phidot]``.
    R : float
        Continuous LQR input weight.
    observer : float
        Kalman filter designed for ``SIGMA_MEAS / observer`` (> 1: trusts the sensors more;
        ``controller_ss``'s ``observer``).
    a_cmd : float
        Force clamp as the cart acceleration it allows from upright (m/s^2).
    ki : float, optional
        The firmware's integral gain on the cart position error (N/(m s); the margin design's,
        :mod:`host.design.margin`).  ``None``: a design without the integral row (and no ``ki``
        in :meth:`as_dict`); ``0``: the row present and zero.
    """

    name: str
    Q: tuple[float, float, float, float]
    R: float
    observer: float = 1.0
    a_cmd: float = 4.4
    ki: float | None = None

    def controller(self, params: RobotParams, *, integral: bool = True) -> Any:
        """The controller the firmware runs for ``params``: the
        :class:`host.design.discrete.DiscreteController` of the weights, inside an
        :class:`~host.design.integral.IntegralController` when ``ki > 0`` (``integral=False``:
        the state feedback and estimator alone, what the export's rows are made from)."""
        from host.design import discrete

        inner = discrete.controller_ss(params, Q=self.Q, R=self.R, u_max=discrete.force_clamp(params, self.a_cmd),
                                       observer=self.observer)
        if integral and self.ki is not None and self.ki > 0:
            return IntegralController(inner, self.ki)
        return inner

    def u_max(self, params: RobotParams) -> float:
        """The force clamp (N) for ``params``."""
        from host.design.discrete import force_clamp

        return force_clamp(params, self.a_cmd)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Candidate":
        """The candidate an :meth:`as_dict` describes (``commission.json`` keeps its designs so)."""
        return cls(str(d["name"]), tuple(float(v) for v in d["Q"]), float(d["R"]),  # type: ignore[arg-type]
                   float(d["observer"]), float(d["a_cmd"]), ki=None if d.get("ki") is None else float(d["ki"]))

    def as_dict(self, params: RobotParams) -> dict[str, Any]:
        """JSON-friendly description (with the clamp in N and the export command)."""
        q = " ".join(f"{v:.6g}" for v in self.Q)
        return {"name": self.name, "Q": list(self.Q), "R": self.R, "observer": self.observer, "a_cmd": self.a_cmd,
                "u_max": self.u_max(params),
                "export": f"upright export --Q {q} --R {self.R:.6g} --observer {self.observer:.6g} "
                          f"--u-max {self.u_max(params):.6g}",
                **({} if self.ki is None else {"ki": self.ki})}


def shipped() -> Candidate:
    """The shipped firmware design (``Q_DEFAULT``, ``R_DEFAULT``, ``OBSERVER_DEFAULT``, ``A_CMD_DEFAULT``)."""
    from host.design.discrete import A_CMD_DEFAULT, OBSERVER_DEFAULT, Q_DEFAULT, R_DEFAULT

    return Candidate("shipped", tuple(float(v) for v in Q_DEFAULT), float(R_DEFAULT), float(OBSERVER_DEFAULT),  # type: ignore[arg-type]
                     float(A_CMD_DEFAULT))


@dataclass
class Evaluation:
    """Metrics of one candidate at every point of the set.

    Attributes
    ----------
    candidate : Candidate
    points : list of Point
    metrics : dict
        ``metrics[scenario][constraint]`` -> ndarray over points (``nan`` where the scenario
        was not run at that point: the push outside its points).  ``settle`` is ``inf`` when
        the run never settles (or falls); :meth:`ratios` turns that into :data:`UNSETTLED`.
    limits : dict
        Constraint limits (``phi_max``, ``a_max``, ``settle``; the square wave's settle limit is
        ``min(t_settle, 2.2 s)``).
    force_lsb : float
        Worst error of the firmware's force command caused by quantising the design's gains
        into the fixed-point table (output LSB of 2**-9 N, :attr:`host.design.export.Row.quant_error`
        of the ``force`` row; :data:`FORCE_LSB_MAX` bounds it).
    """

    candidate: Candidate
    points: list[Point]
    metrics: dict[str, dict[str, np.ndarray]]
    limits: dict[str, dict[str, float]]
    force_lsb: float = math.nan

    def ratios(self, scenario: str, constraint: str) -> np.ndarray:
        """Value / limit per point (> 1 fails; never settled or beyond -> :data:`UNSETTLED`; not run -> nan)."""
        v = self.metrics[scenario][constraint]
        r = v / self.limits[scenario][constraint]
        return np.where(np.isinf(v), UNSETTLED, np.minimum(r, UNSETTLED))

    def worst(self, scenario: str, constraint: str) -> tuple[float, float, int]:
        """``(value, ratio, point index)`` of the worst point (value ``inf``: never settled)."""
        r = self.ratios(scenario, constraint)
        if not np.any(np.isfinite(r)):
            return math.nan, math.nan, -1
        i = int(np.nanargmax(r))
        return float(self.metrics[scenario][constraint][i]), float(r[i]), i

    @property
    def score(self) -> tuple[float, int, float]:
        """Sort key, smaller is better: the worst ratio (capped at a fall), then the number of
        robots (points) where any check fails, then the mean ratio."""
        rs = np.array([self.ratios(s, c) for s in self.metrics for c in CONSTRAINTS])
        fin = rs[np.isfinite(rs)]
        failing = int(np.sum(np.any(np.nan_to_num(rs, nan=0.0) > 1.0, axis=0)))
        return float(np.max(fin)), failing, float(np.mean(fin))

    @property
    def nominal_ok(self) -> bool:
        """Every constraint met at the nominal robot (point 0 of :meth:`UncertaintySet.points`)."""
        rs = [self.ratios(s, c)[0] for s in self.metrics for c in CONSTRAINTS]
        return all(not r > 1.0 for r in rs)  # nan (not run there) counts as met

    @property
    def falls(self) -> int:
        """Robots (points) where the pendulum leaves ``|phi| < phi_max`` in some scenario (lost)."""
        r = np.array([self.ratios(s, "phi_max") for s in self.metrics])
        return int(np.sum(np.any(np.nan_to_num(r, nan=0.0) >= 1.0, axis=0)))

    @property
    def precise(self) -> bool:
        """The firmware carries the design at the precision of the force row's bound
        (:data:`FORCE_LSB_MAX`)."""
        return not self.force_lsb > FORCE_LSB_MAX

    @property
    def rank(self) -> tuple[bool, float, int, int, float]:
        """Ranking key of the search, smaller is better: a design that fails on the nominal
        robot (the model it was designed for) or that the fixed-point table carries less
        precisely than :data:`FORCE_LSB_MAX` after every one that does not; then the worst
        ratio, the robots where the pendulum is lost (a fall is worse than a slow settling,
        and the worst ratio caps both), the robots with any failing check and the mean ratio
        (:attr:`score`)."""
        worst, failing, mean = self.score
        return (not (self.nominal_ok and self.precise), worst, self.falls, failing, mean)

    @property
    def passes(self) -> bool:
        """Every constraint met at every point where each scenario ran."""
        return self.score[0] <= 1.0


def kick_state(values: Mapping[str, float], params: RobotParams, impulse: float = KICK) -> tuple[float, float, float, float]:
    """The state just after a cart impulse at rest, upright (:func:`sim.plant.impulse_jump`, as the
    scenario simulator applies it), for a robot's batch ``values`` (``M``, ``m``, ``I``; ``L`` the model's)."""
    from sim.plant import impulse_jump

    M, m, L, inertia = float(values["M"]), float(values["m"]), float(params.L), float(values["I"])
    dxd, dphid = impulse_jump(0.0, impulse, M + m, m * L, inertia + m * L**2)
    return 0.0, dxd, 0.0, dphid


def _scenario(kind: str, amplitude: float = 0.0, duration: float = RUN_S, point: Point | None = None,
              params: RobotParams | None = None, rate: float = 500.0) -> Any:
    """A :class:`sim.scenario.Scenario` of a batch run (for its metrics, or to replay a corner)."""
    from sim.scenario import load_scenario, scenario_from_dict

    if kind in FORCE_SCENARIOS:
        sc = load_scenario(FORCE_SCENARIOS[kind])
    else:
        d: dict[str, Any] = {"name": f"robust_{kind}", "duration": duration,
                             "description": f"robust design, {kind} from rest (batch run)"}
        if kind == "tilt":
            d["initial"] = {"phi": TILT}
        elif kind == "kick":
            d["description"] = f"robust design, {KICK:g} N s kick on the cart at rest (batch run)"
            if point is not None and params is not None:
                v = kick_state(point.values(params), params)
                d["initial"] = {"xdot": v[1], "phidot": v[3]}
        else:
            d["reference"] = {"kind": "step", "start": 0.0, "amplitude": amplitude}
        sc = scenario_from_dict(d)
    if point is not None and params is not None:
        sc = replace(sc, param_overrides=point.overrides(params), delay=point.delay_ticks / rate,
                     description=f"{sc.description}; robot: {point.label(rate)}")
    return sc


def corner_scenario(kind: str, point: Point, params: RobotParams, sign: float = 1.0) -> Any:
    """The scenario of one run of the robust evaluation at ``point`` (replayable: ``upright simulate``).

    ``kind`` is one of :data:`SCENARIOS`; ``sign`` the direction of the step edge.
    """
    if kind not in SCENARIOS:
        raise ValueError(f"kind must be one of {SCENARIOS}, got {kind!r}")
    dur = {"step": RUN_S, "square": SQUARE_LEVEL, "tilt": RUN_S, "push": 8.0, "kick": KICK_S}[kind]
    return _scenario(kind, sign * STEP, dur, point, params, float(params.rate))


def _metrics_of(traces: Mapping[str, np.ndarray], j: int, scenario: Any, params: RobotParams,
                n_ticks: int) -> tuple[float, float]:
    """Peak |phi| and settling time of batch run ``j`` over its first ``n_ticks``.

    The settling definition of :func:`sim.metrics.compute_metrics` for a scenario with one
    segment (the disturbance at t = 0): phi and, with a reference, x, each into its band
    (2 % of the response, at least the sensor floor); ``nan`` if never settled or fallen.
    """
    from sim.metrics import settling_time

    t = traces["t"][:n_ticks]
    phi = traces["phi"][:n_ticks, j]
    end = float(t[-1] + (t[1] - t[0]))
    floor_phi = 2.0 * params.pot_range / 2**params.adc_bits
    floor_x = 4.0 * math.pi * params.r_wheel / params.enc_cpr
    peak = min(float(np.max(np.abs(phi))), math.pi / 2)  # fallen: lying on the ground (as PlantSim)
    if not abs(float(phi[-1])) < params.phi_max:
        return peak, math.nan
    worst = settling_time(t, phi, t0=0.0, t1=end, floor=floor_phi)
    if scenario.reference.kind != "none" and not math.isnan(worst):
        x = traces["x"][:n_ticks, j]
        tail = x[-max(1, int(round(0.05 * x.size))):]
        scale = max(abs(scenario.reference.amplitude), float(np.max(np.abs(x - np.mean(tail)))))
        worst = max(worst, settling_time(t, x, t0=0.0, t1=end, scale=scale, floor=floor_x))
    return peak, worst


class MeasuredStart:
    """``ctrl`` started the way the firmware starts balancing, for the batch simulator.

    The firmware takes its first estimate of the (delayed) tilt from the first ADC reading
    (:func:`sim.plantsim.run_scenario_float`, ``init="measured"``); the batch starts every
    controller at ``z = 0``.  This wrapper carries the initial tilt on the batch's third input
    (``x_ref``, unused by a tilt run) and adds one state ``e`` with ``e' = v3``: the term
    ``(v3 - e)`` is the initial tilt at tick 0 and zero after, and it enters the output and the
    update exactly as an initial state ``z0 = phi0 * e_phi`` would (``Cc z0``, ``Ac z0``).  The
    back-EMF speed estimate of tick 0 misses that term (``estimator_rows`` has no third
    input): one tick, at rest.  Use it with ``x_ref = phi0`` and a zero reference.
    """

    def __init__(self, ctrl: Any) -> None:
        Ac = np.asarray(ctrl.Ac, dtype=float)
        n = Ac.shape[0]
        Bc = np.asarray(ctrl.Bc, dtype=float).reshape(n, 3)
        Cc = np.asarray(ctrl.Cc, dtype=float).reshape(n)
        Dc = np.asarray(ctrl.Dc, dtype=float).reshape(3)
        Bu = np.asarray(ctrl.Bu, dtype=float).reshape(n)
        z0 = np.zeros(n)
        z0[2] = 1.0  # the a-priori estimate of the delayed tilt
        self.Ac = np.zeros((n + 1, n + 1))
        self.Ac[:n, :n] = Ac
        self.Ac[:n, n] = -Ac @ z0
        self.Bc = np.zeros((n + 1, 3))
        self.Bc[:n, :2] = Bc[:, :2]
        self.Bc[:n, 2] = Ac @ z0
        self.Bc[n, 2] = 1.0
        self.Cc = np.append(Cc, -Cc @ z0)[None, :]
        self.Dc = np.array([[Dc[0], Dc[1], Cc @ z0]])
        self.Bu = np.append(Bu, 0.0)[:, None]
        self.Ts, self.u_max = ctrl.Ts, ctrl.u_max
        self.Ad, self.Bd, self.C, self.M, self.delay_steps = ctrl.Ad, ctrl.Bd, ctrl.C, ctrl.M, ctrl.delay_steps


def _batch_part(params: RobotParams, ctrl: Any, points: Sequence[Point], engine: str | None,
                chunk: int, supply_measured: bool = False) -> dict[str, dict[str, np.ndarray]]:
    """step (+-), square (+- edges in the first 2.2 s), tilt and kick at every point, in the batch."""
    n = len(points)
    kinds = [("up", STEP, 0.0), ("down", -STEP, 0.0), ("tilt", 0.0, TILT), ("kick", 0.0, 0.0)]
    out = {k: {c: np.full(n, -np.inf) for c in CONSTRAINTS} for k in ("step", "square", "tilt", "kick")}
    sc_step = {+1: _scenario("step", STEP), -1: _scenario("step", -STEP)}
    sc_sq = {+1: _scenario("square", STEP, SQUARE_LEVEL), -1: _scenario("square", -STEP, SQUARE_LEVEL)}
    sc_tilt = _scenario("tilt")
    Ts = 1.0 / float(params.rate)
    n_sq = int(round(SQUARE_LEVEL / Ts))
    n_kick = int(round(KICK_S / Ts))
    for k_sel, c in (((0, 1, 3), ctrl), ((2,), MeasuredStart(ctrl))):
        _batch_runs(params, c, points, kinds, k_sel, engine, chunk, out, sc_step, sc_sq, n_sq,
                    {"tilt": (sc_tilt, None), "kick": (_scenario("kick"), n_kick)}, supply_measured)
    return out


def _batch_runs(params: RobotParams, ctrl: Any, points: Sequence[Point], kinds: Sequence[tuple[str, float, float]],
                k_sel: Sequence[int], engine: str | None, chunk: int, out: dict[str, dict[str, np.ndarray]],
                sc_step: Mapping[int, Any], sc_sq: Mapping[int, Any], n_sq: int,
                single: Mapping[str, tuple[Any, int | None]], supply_measured: bool = False) -> None:
    """Run the ``k_sel`` kinds at every point in chunks; ``single``: the kinds scored as one run
    each, ``name -> (scenario, ticks scored or None: the whole run)``."""
    from sim.batch import RunSet, simulate_batch

    runs_all = [(i, kind) for i in range(len(points)) for kind in k_sel]
    for a in range(0, len(runs_all), chunk):
        part = runs_all[a:a + chunk]
        vals = [points[i].values(params) for i, _ in part]
        x0 = np.zeros((len(part), 4))
        x0[:, 2] = [kinds[k][2] for _, k in part]
        for j, (_, k) in enumerate(part):
            if kinds[k][0] == "kick":
                x0[j] = kick_state(vals[j], params)
        rs = RunSet(x0=x0, values={key: np.array([v[key] for v in vals]) for key in vals[0]},
                    delay_ticks=np.array([points[i].delay_ticks for i, _ in part], dtype=np.int64),
                    noise_seed=np.zeros(len(part), dtype=np.int64),
                    x_ref=np.array([kinds[k][1] if kinds[k][0] != "tilt" else kinds[k][2] for _, k in part]))
        res = simulate_batch(params, ctrl, rs, duration=RUN_S, record=True, engine=engine,
                             supply_measured=supply_measured)
        tr = res.traces
        assert tr is not None
        n_full = tr["x"].shape[0]
        for j, (i, k) in enumerate(part):
            acc = float(res.metrics["xddot_max"][j])
            name = kinds[k][0]
            if name in single:  # the kick: the 4.5 s after it, as in impulse_kick
                sc, n_ticks = single[name]
                ph, st = _metrics_of(tr, j, sc, params, n_full if n_ticks is None else n_ticks)
                _worse(out[name], i, ph, acc, st)
                continue
            sgn = 1 if name == "up" else -1
            ph, st = _metrics_of(tr, j, sc_step[sgn], params, n_full)
            _worse(out["step"], i, ph, acc, st)
            ph, st = _metrics_of(tr, j, sc_sq[sgn], params, n_sq)
            _worse(out["square"], i, ph, acc, st)


def _worse(m: dict[str, np.ndarray], i: int, phi: float, acc: float, settle: float) -> None:
    """Keep the worse of the runs at point ``i`` (never settled: ``inf``, the worst)."""
    for key, v in (("phi_max", phi), ("a_max", acc), ("settle", math.inf if math.isnan(settle) else settle)):
        m[key][i] = max(m[key][i], v)


def _force_part(kind: str, params: RobotParams, ctrl: Any, points: Sequence[Point], which: Sequence[int],
                supply_measured: bool = False) -> dict[str, np.ndarray]:
    """A scenario of :data:`FORCE_SCENARIOS` in the scenario simulator at the points ``which`` (nan elsewhere)."""
    out = {c: np.full(len(points), np.nan) for c in CONSTRAINTS}
    for i in which:
        for c, v in zip(CONSTRAINTS, simulate_corner(kind, points[i], params, ctrl, supply_measured=supply_measured)):
            out[c][i] = v
    return out


def simulate_corner(kind: str, point: Point, params: RobotParams, ctrl: Any, sign: float = 1.0, *,
                    supply_measured: bool = False) -> tuple[float, float, float]:
    """One run of the evaluation in the scenario simulator (:func:`sim.plantsim.run_scenario_float`).

    The tilt starts its estimator at the first measured tilt, as the firmware (and the batch
    evaluation, :class:`MeasuredStart`) do; the others start from rest at ``z = 0``.
    ``supply_measured``: the firmware inverts the motor with the robot's supply
    (:attr:`UncertaintySet.supply_measured`).

    Returns
    -------
    (float, float, float)
        Peak ``|phi|``, peak ``|xddot|`` and settling time (``inf``: never settled), the
        scenario metrics of :func:`sim.metrics.compute_metrics`.
    """
    from sim.metrics import compute_metrics
    from sim.plantsim import run_scenario_float

    sc = corner_scenario(kind, point, params, sign)
    log = run_scenario_float(sc, params, ctrl, init="measured" if kind == "tilt" else "zero",
                             supply_measured=supply_measured)
    acc = float(np.max(np.abs(log["xddot"])))
    if kind in FORCE_SCENARIOS:  # several segments: the scenario metrics as they are
        m = compute_metrics(log, sc, params)
        peak, settle = m.peak_phi, m.settling_time
    else:  # one segment: the same definition, also for a run that falls
        peak, settle = _metrics_of({"t": log["t"], "x": log["x"][:, None], "phi": log["phi"][:, None]}, 0, sc, params,
                                   len(log["t"]))
    return peak, acc, math.inf if math.isnan(settle) else settle


def evaluate(params: RobotParams, cand: Candidate, uset: UncertaintySet, *, push: bool = True,
             engine: str | None = None, chunk: int = 192, points: Sequence[Point] | None = None) -> Evaluation:
    """Score ``cand`` at every point of ``uset`` (see the module docstring).

    Parameters
    ----------
    params : RobotParams
        The design model (the nominal robot, the firmware's parameters).
    cand : Candidate
    uset : UncertaintySet
    push : bool
        Run the push at the nominal point and ``uset.push_points`` worst points;
        ``False``: at the nominal point only, and only when the batch scenarios pass there
        (enough for :attr:`Evaluation.nominal_ok`, the search's first criterion).
    engine : str, optional
        Batch engine (default numba when importable).
    chunk : int
        Runs per batch call (memory: traces of ``chunk`` runs).
    points : sequence of Point, optional
        Evaluate at these points instead of ``uset.points(...)``.

    Returns
    -------
    Evaluation
    """
    rate = float(params.rate)
    pts = list(points) if points is not None else uset.points(rate, params.delay)
    ctrl = cand.controller(params)
    metrics: dict[str, dict[str, np.ndarray]] = _batch_part(params, ctrl, pts, engine, chunk, uset.supply_measured)
    lim = {"phi_max": float(params.phi_max), "a_max": float(params.a_max), "settle": float(params.t_settle)}
    limits = {s: dict(lim) for s in SCENARIOS}
    limits["square"]["settle"] = min(float(params.t_settle), SQUARE_LEVEL)
    limits["kick"]["a_max"] = math.inf  # not a constraint for a Dirac kick (module docstring)
    from host.design.export import export

    force = next(r for r in export(params, ctrl).rows if r.name == "force")
    ev = Evaluation(cand, pts, metrics, limits, force_lsb=force.quant_error)
    if push:
        per_point = np.max([ev.ratios(s, c) for s in metrics for c in CONSTRAINTS], axis=0)
        which = [0, *[int(i) for i in np.argsort(-per_point, kind="stable") if i != 0][: uset.push_points]]
    else:
        which = [0] if ev.nominal_ok else []
    for kind in FORCE_SCENARIOS:
        metrics[kind] = _force_part(kind, params, ctrl, pts, which, uset.supply_measured)
    return ev


def worst_rows(ev: Evaluation, params: RobotParams) -> list[dict[str, Any]]:
    """The worst case per scenario and constraint (where it is one): value, limit, ratio, PASS/FAIL and the robot."""
    rows = []
    rate = float(params.rate)
    for s in SCENARIOS:
        if s not in ev.metrics:
            continue
        ran = int(np.sum(np.isfinite(ev.ratios(s, "phi_max"))))
        for c in CONSTRAINTS:
            lim = ev.limits[s][c]
            if math.isinf(lim):
                continue  # not a constraint of this scenario (the kick's acceleration)
            v, r, i = ev.worst(s, c)
            rows.append({"scenario": s, "constraint": c, "worst": v, "limit": lim, "ratio": r,
                         "verdict": "PASS" if r <= 1.0 else "FAIL", "points": ran,
                         "fails": int(np.sum(ev.ratios(s, c) > 1.0)), "at": ev.points[i].label(rate) if i >= 0 else "",
                         "point": i})
    return rows


def plant_toml(point: Point, params: RobotParams) -> str:
    """A complete robot TOML of the robot at ``point`` (for ``--plant``: the design keeps ``params``)."""
    vals = dict(params.values)
    vals.update(point.overrides(params))
    vals["sensors.delay"] = point.delay_ticks / float(params.rate)
    sections: dict[str, list[str]] = {}
    for k, v in vals.items():
        if isinstance(v, float) and math.isnan(v):
            continue  # derived from the geometry
        sec, key = k.split(".", 1)
        sections.setdefault(sec, []).append(f"{key} = {int(v) if float(v).is_integer() and key in _INTS else repr(float(v))}")
    head = f"# robust design corner: {point.label(float(params.rate))} (of {params.source})\n"
    return head + "\n".join(f"\n[{sec}]\n" + "\n".join(lines) for sec, lines in sections.items()) + "\n"


_INTS = ("n_motors", "adc_bits", "pot_offset", "enc_cpr", "rate")
