"""Vectorised closed-loop simulation of many runs at once (numpy over a batch axis).

Every run is the same loop the firmware closes on the real robot, with its own physical
parameters, measurement delay, noise stream and initial state::

    tick k (period Ts = 1/rate):
        reading  = sensors(x, phi, noise_k)          ADC / encoder counts (sim.sensors)
        v        = decode(reading from d_i ticks ago)  [x_meas, phi_meas, x_ref]
        u        = Cc z + Dc v ; u_sat = clip(u, +-u_max)
        z        = Ac z + Bc v + Bu u_sat             (host.design.discrete.DiscreteController)
        duty     = duty_from_force(u_sat, xdot_est)  back-EMF compensation (sim.motor)
    between ticks: RK4 sub-steps at ``plant_rate`` (1 kHz) of sim.plant.dynamics with the
    force F = force_from_duty(duty, xdot) of the *true* motor (it varies with xdot inside
    the tick, as a real H-bridge's does).

``drive="force"`` skips the motor model (F = u_sat, the report's ideal force actuator).
The run's state lives in arrays of shape ``(4, N)``; per-run parameters are arrays of
shape ``(N,)`` handed to the broadcasting models of :mod:`sim.plant` and :mod:`sim.motor`.

Randomness is per run, never per batch: run ``i`` draws its noise from
``numpy.random.default_rng(noise_seed[i])`` exactly as a single-run
:class:`sim.sensors.NoiseSource` would, so a run's result does not depend on which
batch, chunk or machine simulated it (the Dask scale-out relies on this).  For the same
reason the controller's linear algebra is a sum over the columns in a fixed order and not a
BLAS product: BLAS kernels round a column differently depending on where it sits in the
matrix.

Two engines compute the same thing (``engine=``): ``"numpy"``, the reference above,
vectorised over the batch tick by tick; ``"numba"`` (the default when numba is installed),
the compiled kernel of :mod:`sim.batch_kernel`, run by run on all cores, **bit-identical** to
the reference per run (metrics and traces; see that module for what makes it so).

Plant realism (dry friction, gear backlash with the encoder on the motor shaft, the bridge's
deadband and minimum duty, pot nonlinearity; :data:`REALISM_KEYS`, per run; docs/parameters.md,
"Plant realism"): when any run has it, both engines take a path that decides the gear's contact
and stuck/sliding at each RK4 sub-step's start and holds them over it; that path leaves an ideal
run's arithmetic exactly as the ideal path's, so a run's result still does not depend on its batch.

The firmware side (count conversion, motor inversion, controller) always uses the
*nominal* parameters; only the plant and the motor that turns duty into force are the
run's true ones -- that is what parameter uncertainty means for the real robot.

:func:`closed_loop_iosys` is the same loop for one run as a python-control discrete-time
``nlsys`` (scalar code written independently of the batch code); :func:`simulate_run`
drives it with ``control.input_output_response``.  Tests compare the two trajectory by
trajectory; ``make bench`` times both.
"""

from __future__ import annotations

import math
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import numpy as np

from .motor import MOTOR_KEYS, bridge_fraction, duty_from_force, force_from_duty
from .params import SCHEMA, RobotParams
from .plant import dynamics, rk4_step
from .sensors import (
    NoiseModel,
    adc_to_phi,
    enc_counts_per_m,
    encoder_delta,
    inl_terms,
    phi_to_adc,
    x_to_encoder,
)

__all__ = [
    "BatchError",
    "PLANT_KEYS",
    "REALISM_KEYS",
    "VARIED_KEYS",
    "METRICS",
    "RunSet",
    "BatchResult",
    "estimator_rows",
    "simulate_batch",
    "ENGINES",
    "default_engine",
    "closed_loop_iosys",
    "closed_loop_x0",
    "simulate_run",
    "draw_noise",
]

PLANT_KEYS = ("M", "m", "L", "I", "b", "g")
"""Physical parameters of the equations of motion that may vary per run."""

REALISM_KEYS = ("coulomb", "stiction", "backlash", "deadband", "duty_min", "pot_inl")
"""Plant-realism parameters that may vary per run (``docs/parameters.md``, "Plant realism"); 0 = ideal."""

VARIED_KEYS = PLANT_KEYS + ("V_supply", "R", "kt") + REALISM_KEYS
"""Every parameter a :class:`RunSet` may give per run (the true robot of that run).

Sensor and geometry parameters (``r_wheel``, ``gear``, ``enc_cpr``, ``pot_range``,
``pot_offset``, ``pot_inl_cycles``) stay nominal: the firmware converts counts with them, so
they are known exactly (the pot's nonlinearity ``pot_inl``, which the firmware does not know,
may vary).
"""

_REAL_DOTTED = {k.split(".", 1)[1]: k for k in SCHEMA if k.split(".", 1)[1] in REALISM_KEYS}

METRICS = (
    "phi_max",
    "x_max",
    "xddot_max",
    "force_max",
    "settle",
    "phi_rms",
    "force_rms",
    "fallen",
)
"""Per-run metrics of :class:`BatchResult` (see :func:`simulate_batch`)."""

_FALLEN = math.pi / 2  # |phi| beyond this: the pendulum has fallen over
_NOISE_BLOCK = 64  # ticks of noise drawn per run at a time


class BatchError(ValueError):
    """Inconsistent batch inputs (shapes, unknown keys, bad options)."""


@dataclass(frozen=True)
class RunSet:
    """The per-run inputs of a batch of ``N`` closed-loop runs.

    Parameters
    ----------
    x0 : ndarray, shape (N, 4)
        Initial plant states ``[x, xdot, phi, phidot]``.
    values : mapping of str to ndarray (N,)
        True parameter values of each run for any of :data:`VARIED_KEYS`; a key not
        given is nominal in every run.
    delay_ticks : ndarray of int, shape (N,), optional
        Measurement delay of each run in whole control ticks (>= 0; default 0).
    noise_seed : ndarray of int, shape (N,), optional
        Seed of each run's noise generator, ``default_rng(seed)`` (default ``0..N-1``).
    x_ref : float or ndarray, shape (N,), optional
        Cart position reference (m), held for the run (default 0).

    Raises
    ------
    BatchError
        On a wrong shape, an unknown or non-physical parameter, a negative delay or seed.
    """

    x0: np.ndarray
    values: Mapping[str, np.ndarray] = field(default_factory=dict)
    delay_ticks: np.ndarray | None = None
    noise_seed: np.ndarray | None = None
    x_ref: np.ndarray | None = None

    def __post_init__(self) -> None:
        x0 = np.atleast_2d(np.asarray(self.x0, dtype=float))
        if x0.ndim != 2 or x0.shape[1] != 4 or not np.all(np.isfinite(x0)):
            raise BatchError(f"x0 must be finite with shape (N, 4), got shape {np.shape(self.x0)}")
        n = x0.shape[0]
        object.__setattr__(self, "x0", x0)
        vals = {}
        for k, v in dict(self.values).items():
            if k not in VARIED_KEYS:
                raise BatchError(f"cannot vary {k!r} per run (variable: {', '.join(VARIED_KEYS)})")
            try:
                a = np.broadcast_to(np.asarray(v, dtype=float), (n,)).copy()
            except ValueError as exc:
                raise BatchError(f"per-run {k} must be a number or {n} numbers, got shape {np.shape(v)}") from exc
            if k in REALISM_KEYS:
                sp = SCHEMA[_REAL_DOTTED[k]]
                if not np.all(np.isfinite(a)) or np.any(a < sp.lo) or np.any(a > sp.hi):
                    raise BatchError(f"per-run {k} must be finite, in {sp.lo:g} .. {sp.hi:g} {sp.unit} ({sp.doc})")
            elif not np.all(np.isfinite(a)) or np.any(a <= 0) and k != "b" or np.any(a < 0):
                raise BatchError(f"per-run {k} must be finite and positive")
            vals[k] = a
        object.__setattr__(self, "values", vals)
        d = np.zeros(n, dtype=np.int64) if self.delay_ticks is None else np.asarray(self.delay_ticks)
        if d.shape != (n,) or not np.issubdtype(d.dtype, np.integer) or np.any(d < 0):
            raise BatchError(f"delay_ticks must be {n} non-negative ints")
        object.__setattr__(self, "delay_ticks", d.astype(np.int64))
        s = np.arange(n, dtype=np.int64) if self.noise_seed is None else np.asarray(self.noise_seed)
        if s.shape != (n,) or not np.issubdtype(s.dtype, np.integer) or np.any(s < 0):
            raise BatchError(f"noise_seed must be {n} non-negative ints")
        object.__setattr__(self, "noise_seed", s)
        try:
            r = np.zeros(n) if self.x_ref is None else np.broadcast_to(np.asarray(self.x_ref, dtype=float), (n,)).copy()
        except ValueError as exc:
            raise BatchError(f"x_ref must be a number or {n} numbers") from exc
        object.__setattr__(self, "x_ref", r)

    def __len__(self) -> int:
        return self.x0.shape[0]

    def subset(self, index: np.ndarray | slice) -> "RunSet":
        """The runs selected by ``index`` (a slice, integer or boolean array)."""
        return RunSet(
            x0=self.x0[index],
            values={k: v[index] for k, v in self.values.items()},
            delay_ticks=self.delay_ticks[index],
            noise_seed=self.noise_seed[index],
            x_ref=self.x_ref[index],
        )

    def true_params(self, nominal: RobotParams, i: int | None = None) -> dict[str, Any]:
        """Mapping of the true plant and motor parameters (arrays, or run ``i``'s floats)."""
        out: dict[str, Any] = dict(nominal.physical)
        out.update({k: getattr(nominal, k) for k in MOTOR_KEYS})
        out.update({k: nominal.values[_REAL_DOTTED[k]] for k in REALISM_KEYS})
        for k, v in self.values.items():
            out[k] = v if i is None else float(v[i])
        return out


@dataclass
class BatchResult:
    """Metrics (and optionally traces) of a batch.

    Attributes
    ----------
    metrics : dict of str to ndarray (N,)
        :data:`METRICS`: ``phi_max`` (rad), ``x_max`` (m), ``xddot_max`` (m/s^2),
        ``force_max`` (N, applied), ``settle`` (s, ``inf`` if not settled),
        ``phi_rms`` (rad) and ``force_rms`` (N) over the final ``window``,
        ``fallen`` (bool, ``|phi|`` passed pi/2).
    traces : dict of str to ndarray (T, N), or None
        With ``record=True``: ``t`` (T,), ``x, xdot, phi, phidot`` at every tick,
        ``u_sat`` (N), ``force`` (N, at the start of the tick), ``duty``,
        ``x_meas, phi_meas``.
    """

    metrics: dict[str, np.ndarray]
    traces: dict[str, np.ndarray] | None = None


def estimator_rows(ctrl: Any) -> tuple[np.ndarray, np.ndarray] | None:
    """The controller's cart-speed estimate as a linear map ``xdot_est = ce z + de v``.

    Built from the structured pieces of :class:`host.design.discrete.DiscreteController`
    (``Ad, Bd, C, M, delay_steps``), the same prediction as its ``estimate()``.
    Returns ``None`` for a controller without them.
    """
    try:
        Ad, Bd, C, M, d = ctrl.Ad, ctrl.Bd, ctrl.C, ctrl.M, int(ctrl.delay_steps)
    except AttributeError:
        return None
    n = ctrl.Ac.shape[0]
    Phi = np.linalg.matrix_power(Ad, d)
    ce = np.zeros((4, n))
    de = np.zeros((4, 3))
    ce[:, :4] = Phi @ (np.eye(4) - M @ C)
    de[:, :2] = Phi @ M
    for i in range(d):
        ce[:, 4 + i] = (np.linalg.matrix_power(Ad, d - 1 - i) @ Bd)[:, 0]
    return ce[1].copy(), de[1].copy()


def _linear_part(ctrl: Any, drive: str) -> tuple[np.ndarray, np.ndarray]:
    # one matrix for the whole linear part: rows [u; xdot_est; z'] from columns [z; v]
    Ac, Bc, Cc, Dc, Bu = _ctrl_matrices(ctrl)
    nz = Ac.shape[0]
    G = np.zeros((nz + 2, nz + 3))
    G[0, :nz], G[0, nz:] = Cc, Dc
    if drive == "motor":
        est = estimator_rows(ctrl)
        if est is None:
            raise BatchError("drive='motor' needs the controller's speed estimate (Ad, Bd, C, M)")
        G[1, :nz], G[1, nz:] = est
    G[2:, :nz], G[2:, nz:] = Ac, Bc
    return G, Bu


def _ctrl_matrices(ctrl: Any) -> tuple[np.ndarray, ...]:
    Ac = np.asarray(ctrl.Ac, dtype=float)
    n = Ac.shape[0]
    Bc = np.asarray(ctrl.Bc, dtype=float).reshape(n, 3)
    Cc = np.asarray(ctrl.Cc, dtype=float).reshape(n)
    Dc = np.asarray(ctrl.Dc, dtype=float).reshape(3)
    Bu = getattr(ctrl, "Bu", None)
    Bu = np.zeros(n) if Bu is None else np.asarray(Bu, dtype=float).reshape(n)
    return Ac, Bc, Cc, Dc, Bu


def draw_noise(model: NoiseModel, Ts: float, seeds: np.ndarray, start: int, ticks: int) -> np.ndarray:
    """Noise ``[n_x, n_phi]`` of ticks ``start .. start+ticks-1`` for each run, shape (ticks, 2, N).

    Run ``i`` draws from ``default_rng(seeds[i])`` in the order a single-run
    :class:`sim.sensors.NoiseSource` draws (one ``(2,)`` sample per held period).  The
    generators are created afresh and advanced to ``start`` (``start`` must be a
    multiple of the hold period); callers that stream keep their own generators
    (see :class:`_NoiseStream`).
    """
    s = _NoiseStream(model, Ts, seeds)
    if start:
        s.take(start)
    return s.take(ticks)


def _noise_scale(model: NoiseModel, Ts: float) -> tuple[float, float]:
    """``(offset, scale)`` that turn a generator's draw into the noise value.

    ``uniform``: ``lo + (hi - lo) * next_double`` (numpy's own ``uniform``), ``white``:
    ``standard_normal * std``; the numpy streams and the compiled kernel both use these.
    """
    if model.kind == "uniform":
        lo, hi = -model.amplitude, model.amplitude
        return lo, hi - lo
    return 0.0, (model.std(Ts) if model.kind == "white" else 0.0)


class _NoiseStream:
    """Per-run noise generators, read in blocks of ticks."""

    def __init__(self, model: NoiseModel, Ts: float, seeds: np.ndarray) -> None:
        self.model = model
        self.n = len(seeds)
        self.hold = model.hold_ticks(Ts)
        self.off, self.scale = _noise_scale(model, Ts)
        self.mask = np.array([[c in model.channels] for c in ("x", "phi")], dtype=float)  # (2, 1)
        self.rngs = [np.random.default_rng(int(s)) for s in seeds] if model.kind != "none" else []
        self.pos = 0

    def _raw(self, ticks: int) -> np.ndarray | None:
        # the next ``ticks`` ticks' draws, one per hold period, run-major (n, draws, 2) and
        # scaled; None when there is no noise
        if self.model.kind == "none" or ticks == 0:
            return None
        if self.pos % self.hold:
            raise BatchError("noise blocks must start on a hold boundary")
        raw = np.empty((self.n, -(-ticks // self.hold), 2))
        # fill each run's block in place with the generator's own fill loops; the values
        # are bit-identical to ``standard_normal(shape) * std`` and ``uniform(lo, hi, shape)``
        # (numpy computes uniform as ``lo + (hi - lo) * next_double``)
        if self.model.kind == "white":
            for i, g in enumerate(self.rngs):
                g.standard_normal(out=raw[i])
            raw *= self.scale
        else:
            for i, g in enumerate(self.rngs):
                g.random(out=raw[i])
            raw = self.off + self.scale * raw
        return raw

    def take(self, ticks: int) -> np.ndarray:
        """The next ``ticks`` ticks' noise, tick-major: shape ``(ticks, 2, N)``."""
        raw = self._raw(ticks)
        self.pos += ticks
        if raw is None:
            return np.zeros((ticks, 2, self.n))
        out = np.ascontiguousarray(raw.transpose(1, 2, 0)) * self.mask
        return np.repeat(out, self.hold, axis=0)[:ticks] if self.hold > 1 else out

    def take_runs(self, ticks: int) -> np.ndarray:
        """Like :meth:`take` (the same values), run-major: shape ``(N, ticks, 2)``."""
        raw = self._raw(ticks)
        self.pos += ticks
        if raw is None:
            return np.zeros((self.n, ticks, 2))
        out = raw * self.mask[:, 0]
        if self.hold > 1:
            out = np.repeat(out, self.hold, axis=1)[:, :ticks]
        return np.ascontiguousarray(out)


ENGINES = ("numpy", "numba")
"""Implementations of :func:`simulate_batch`: the numpy reference and the compiled kernel."""


def default_engine() -> str:
    """``"numba"`` when numba is importable, else ``"numpy"``."""
    from . import batch_kernel

    return "numba" if batch_kernel.AVAILABLE else "numpy"


KERNEL_CHUNK: int | None = None
"""Runs per compiled-kernel call; None: :func:`kernel_chunk` (sized to the kernel's threads)."""


def kernel_chunk(n_runs: int, threads: int, lanes: int, noise_in_memory: bool) -> int:
    """Runs per call of the compiled kernel for a batch of ``n_runs`` on ``threads`` threads.

    The kernel spreads a call's groups of ``lanes`` runs over the threads, so a call gives
    each thread at least :data:`_GROUPS_PER_THREAD` groups (the threads finish together).
    With the noise drawn in the kernel a batch takes :data:`_PROGRESS_CALLS` calls (progress
    reports; the generators of the next call are created while the kernel runs); when the
    noise is drawn beforehand (``noise_in_memory``: numpy without the C draw functions) a
    call holds ``runs x ticks x 16`` bytes of noise, so calls stay near
    :data:`_NOISE_CHUNK_RUNS` runs.  The calls are equal, in whole lane groups.
    """
    per_call = lanes * max(1, threads) * _GROUPS_PER_THREAD
    if noise_in_memory:
        per_call = max(per_call, _NOISE_CHUNK_RUNS)
    else:
        per_call = max(per_call, -(-n_runs // _PROGRESS_CALLS))
    # equal calls, each a whole number of lane groups (no short group but the last)
    calls = max(1, -(-n_runs // per_call))
    size = -(-n_runs // calls)
    return max(1, min(n_runs, -(-size // lanes) * lanes))


_GROUPS_PER_THREAD = 8
_NOISE_CHUNK_RUNS = 2048
_PROGRESS_CALLS = 4


def simulate_batch(
    params: RobotParams,
    ctrl: Any,
    runs: RunSet,
    *,
    duration: float = 5.0,
    noise: NoiseModel | None = None,
    drive: str = "motor",
    plant_rate: float = 1000.0,
    settle_band: float = 0.005,
    window: float = 1.0,
    accel_limit: float | None = None,
    record: bool = False,
    progress: Callable[[int, int], None] | None = None,
    ctrl_index: np.ndarray | None = None,
    plant: RobotParams | None = None,
    engine: str | None = None,
    supply_measured: bool = False,
) -> BatchResult:
    """Simulate every run of ``runs`` in closed loop with the discrete controller.

    Parameters
    ----------
    params : RobotParams
        Nominal parameters: the firmware's (sensor conversion, motor inversion, loop
        rate) and, without ``plant``, the defaults of every run's true plant.
    ctrl : DiscreteController or sequence of them
        The controller (``Ac, Bc, Cc, Dc, Bu, Ts, u_max``), see :mod:`host.design.discrete`; or
        several (same period and state size) with ``ctrl_index`` choosing one per run,
        so that many designs run in one batch.
    runs : RunSet
        Per-run parameters, delays, seeds, initial states, references.
    duration : float
        Simulated time per run (s).
    noise : sim.sensors.NoiseModel, optional
        Measurement noise (default none); each run has its own stream.
    drive : {"motor", "force"}
        ``"motor"``: the force command goes through the firmware's inverse motor model
        (with the controller's speed estimate) to a duty, and the true motor turns the
        duty into force.  ``"force"``: the saturated force is applied as is.
    plant_rate : float
        RK4 step rate (Hz); rounded up to a whole number of sub-steps per tick.
    settle_band : float
        ``settle`` is the time after which ``|phi|`` stays within this band (rad); the
        default 0.005 rad (0.3 deg, ~4 ADC counts) sits well above the noise floor.
    window : float
        ``phi_rms`` and ``force_rms`` are taken over the final ``window`` seconds.
    accel_limit : float, optional
        If given, the applied force is clipped so that ``|xddot| <= accel_limit`` at each
        RK4 evaluation (a drive that cannot accelerate the cart harder).
    record : bool
        Keep per-tick traces (memory ``~ 10 * T * N`` floats).
    progress : callable, optional
        ``progress(ticks_done, ticks_total)`` called now and then (the numba engine: after
        each chunk of runs, in ticks of the whole batch).
    ctrl_index : ndarray of int, shape (N,), optional
        With a sequence of controllers: the controller of each run.
    plant : RobotParams, optional
        The simulated robot when it differs from the design (``--plant``): the defaults of
        every run's true plant and motor (``runs.values`` still override per run), and the
        sensors that produce the counts (``pot_offset``, ``pot_range``, ``adc_bits``,
        ``enc_cpr``, ``r_wheel``); the firmware still decodes the counts and inverts the
        motor with ``params``.  Default: ``params``.
    engine : {"numba", "numpy"}, optional
        ``"numpy"``: the reference, vectorised over the batch.  ``"numba"``: the compiled
        kernel (:mod:`sim.batch_kernel`), bit-identical per run, run by run on all of
        numba's threads.  Default: numba when importable.
    supply_measured : bool
        The firmware measures the motor supply and inverts the motor with it instead of the
        nominal ``V_supply`` (``firmware/motor.py`` ``Motor.set_supply``: the default board's
        divider, ``firmware/board.py`` ``VSUP_ADC_PIN``), modelled as an exact measurement of
        each run's true supply (the firmware's Q12 scale and 9 mV ADC step are below 0.05 %).
        Default ``False``: a board without the divider, the duty for the nominal supply.

    Returns
    -------
    BatchResult

    Raises
    ------
    BatchError
        On a bad option.
    """
    if drive not in ("motor", "force"):
        raise BatchError(f"drive must be 'motor' or 'force', got {drive!r}")
    if not (duration > 0 and plant_rate > 0 and settle_band > 0 and window > 0):
        raise BatchError("duration, plant_rate, settle_band and window must be > 0")
    engine = default_engine() if engine is None else engine
    if engine not in ENGINES:
        raise BatchError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    if engine == "numba":
        from . import batch_kernel

        if not batch_kernel.AVAILABLE:
            raise BatchError("engine='numba' needs numba (pip install numba), or use engine='numpy'")
    noise = NoiseModel() if noise is None else noise
    stacked = isinstance(ctrl, (list, tuple))
    ctrls = list(ctrl) if stacked else [ctrl]
    if not ctrls:
        raise BatchError("no controller given")
    Gs, Bus = [], []
    for c in ctrls:
        G, Bu = _linear_part(c, drive)
        if Gs and G.shape != Gs[0].shape:
            raise BatchError("stacked controllers must have the same number of states (same delay_steps)")
        Gs.append(G)
        Bus.append(Bu)
    Ts = float(ctrls[0].Ts)
    if any(float(c.Ts) != Ts for c in ctrls):
        raise BatchError("stacked controllers must share the sample period")
    u_maxes = np.array([float(c.u_max) for c in ctrls])
    if stacked:
        idx = np.asarray(ctrl_index) if ctrl_index is not None else None
        if idx is None or idx.shape != (len(runs),) or not np.issubdtype(idx.dtype, np.integer) \
                or np.any(idx < 0) or np.any(idx >= len(ctrls)):
            raise BatchError(f"ctrl_index must give each of the {len(runs)} runs a controller index < {len(ctrls)}")
        idx = idx.astype(np.int64)
    else:
        if ctrl_index is not None:
            raise BatchError("ctrl_index needs a sequence of controllers")
        idx = np.zeros(len(runs), dtype=np.int64)
    N = len(runs)
    n_ticks = int(round(duration / Ts))
    sub = max(1, math.ceil(Ts * plant_rate - 1e-9))
    h = Ts / sub
    base = params if plant is None else plant
    true = runs.true_params(base)
    realv = {k: _per_run(true[k], N) for k in REALISM_KEYS}
    real_on = any(bool(np.any(v != 0.0)) for v in realv.values())
    motor_true = {k: true[k] for k in MOTOR_KEYS}
    sens_plant = {k: getattr(base, k) for k in _SENSOR_KEYS}
    if real_on:
        motor_true.update(deadband=true["deadband"], duty_min=true["duty_min"])
        sens_plant.update(pot_inl=true["pot_inl"], pot_inl_cycles=base.pot_inl_cycles)
    setup = _Setup(
        N=N, n_ticks=n_ticks, sub=sub, h=h, Ts=Ts, stacked=stacked, idx=idx,
        Gs=np.stack(Gs), Bus=np.stack(Bus), u_maxes=u_maxes,
        phys={k: true[k] for k in PLANT_KEYS},
        motor_true=motor_true,
        motor_nom={k: true[k] if supply_measured and k == "V_supply" else getattr(params, k) for k in MOTOR_KEYS},
        supply_measured=bool(supply_measured),
        sens_plant=sens_plant,
        real=_Realism(realv) if real_on else None,
        sens_fw={k: getattr(params, k) for k in _SENSOR_KEYS},
        drive=drive, noise=noise, accel_limit=accel_limit, settle_band=settle_band,
        w0=n_ticks * sub - int(round(window / h)), record=record, progress=progress,
    )
    acc, tr = (_loop_numba if engine == "numba" else _loop_numpy)(setup, runs)
    n_samples = n_ticks * sub
    last_out = acc["last_out"]
    settle = np.where(last_out < 0, 0.0, (last_out + 1) * h)
    settle[last_out >= n_samples] = np.inf
    nrm = max(n_samples - max(setup.w0, 0), 1)
    metrics = {
        "phi_max": acc["phi_max"],
        "x_max": acc["x_max"],
        "xddot_max": acc["xddot_max"],
        "force_max": acc["force_max"],
        "settle": settle,
        "phi_rms": np.sqrt(acc["phi_sq"] / nrm),
        "force_rms": np.sqrt(acc["f_sq"] / nrm),
        "fallen": acc["phi_max"] > _FALLEN,
    }
    if progress is not None:
        progress(n_ticks, n_ticks)
    return BatchResult(metrics=metrics, traces=tr)


_SENSOR_KEYS = ("adc_bits", "pot_range", "pot_offset", "enc_cpr", "r_wheel")
_TRACES = ("x", "xdot", "phi", "phidot", "u_sat", "force", "duty", "x_meas", "phi_meas")


class _Realism:
    """Per-run plant-realism constants of a batch (docs/parameters.md, "Plant realism")."""

    def __init__(self, v: Mapping[str, np.ndarray]) -> None:
        self.fc = v["coulomb"]  # N, sliding friction
        self.fs = np.maximum(v["stiction"], v["coulomb"])  # N, breakaway force
        self.fric = self.fs > 0.0
        self.hp = 0.5 * v["backlash"]  # m, half the gear play
        self.play = self.hp > 0.0


@dataclass
class _Setup:
    """What both engines of :func:`simulate_batch` start from."""

    N: int
    n_ticks: int
    sub: int
    h: float
    Ts: float
    stacked: bool
    idx: np.ndarray  # (N,) controller of each run
    Gs: np.ndarray  # (NG, nz+2, nz+3)
    Bus: np.ndarray  # (NG, nz)
    u_maxes: np.ndarray  # (NG,)
    phys: dict[str, Any]
    motor_true: dict[str, Any]
    motor_nom: dict[str, Any]  # V_supply per run when supply_measured
    supply_measured: bool
    sens_plant: dict[str, Any]
    sens_fw: dict[str, Any]
    real: _Realism | None
    drive: str
    noise: NoiseModel
    accel_limit: float | None
    settle_band: float
    w0: int
    record: bool
    progress: Callable[[int, int], None] | None


def _matmul_cols(G: np.ndarray, W: np.ndarray) -> np.ndarray:
    # out[i, n] = sum_j G[i, j(, n)] W[j, n], summed column by column in order j = 0, 1, ...:
    # a fixed operation order (no BLAS, no einsum kernel that may fuse or reorder), the same
    # for a run whatever the batch, and the order the compiled kernel uses
    if G.ndim == 2:
        out = G[:, 0, None] * W[0]
        for j in range(1, G.shape[1]):
            out = out + G[:, j, None] * W[j]
    else:
        out = G[:, 0, :] * W[0]
        for j in range(1, G.shape[1]):
            out = out + G[:, j, :] * W[j]
    return out


def _loop_numpy(s: _Setup, runs: RunSet) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray] | None]:
    """The reference: numpy over the batch axis, tick by tick."""
    N, n_ticks, sub, h, Ts = s.N, s.n_ticks, s.sub, s.h, s.Ts
    nz = s.Bus.shape[1]
    if s.stacked:
        # per-run matrices, batch axis last: the same arithmetic for a run whatever the batch
        G = np.ascontiguousarray(s.Gs[s.idx].transpose(1, 2, 0))
        Bu_col = np.ascontiguousarray(s.Bus[s.idx].T)
        u_max: float | np.ndarray = s.u_maxes[s.idx]
    else:
        G = s.Gs[0]
        Bu_col = s.Bus[0][:, None]
        u_max = float(s.u_maxes[0])
    phys, motor_true, motor_nom = s.phys, s.motor_true, s.motor_nom
    sens, sens_fw = s.sens_plant, s.sens_fw
    cpm = enc_counts_per_m(sens_fw)
    accel_limit, settle_band, drive = s.accel_limit, s.settle_band, s.drive

    X = runs.x0.T.copy()  # (4, N) plant states
    W = np.zeros((nz + 3, N))  # [z; v] controller state and inputs
    W[nz + 2] = runs.x_ref
    d = runs.delay_ticks
    L = int(d.max()) + 1 if N else 1
    cols = np.arange(N)
    enc0 = x_to_encoder(X[0], sens)
    adc0 = phi_to_adc(X[2], sens)
    ring_enc = np.repeat(enc0[None], L, axis=0)  # (L, N) delay line of counts (noiseless start)
    ring_adc = np.repeat(adc0[None], L, axis=0)
    flat_enc, flat_adc = ring_enc.reshape(-1), ring_adc.reshape(-1)
    enc_last = enc0.copy()
    enc_total = encoder_delta(enc0, 0)
    stream = _NoiseStream(s.noise, Ts, runs.noise_seed)
    blk = stream.hold * max(1, _NOISE_BLOCK // stream.hold)
    nblock = np.zeros((0, 2, N))

    phi_max = np.abs(X[2])
    x_max = np.abs(X[0])
    xdd_max = np.zeros(N)
    f_max = np.zeros(N)
    last_out = np.where(phi_max > settle_band, 0, -1).astype(np.int64)  # sample index
    w0 = s.w0  # first sample of the RMS window
    phi_sq = np.zeros(N)
    f_sq = np.zeros(N)
    tr: dict[str, np.ndarray] | None = None
    if s.record:
        tr = {k: np.zeros((n_ticks + 1, N)) for k in _TRACES}
        tr["t"] = np.arange(n_ticks + 1) * Ts
    if accel_limit is not None:
        zeros, ones = np.zeros(N), np.ones(N)

    def rhs(x: np.ndarray, duty: np.ndarray | None, us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        F = us if duty is None else force_from_duty(duty, x[1], motor_true)
        if accel_limit is not None:
            # xddot is affine in F: clip F to the range that keeps |xddot| <= accel_limit
            a0 = dynamics(0.0, x, zeros, phys)[1]
            a1 = dynamics(0.0, x, ones, phys)[1] - a0
            F = np.clip(F, (-accel_limit - a0) / a1, (accel_limit - a0) / a1)
        return dynamics(0.0, x, F, phys), F

    rl = s.real
    if rl is not None:
        # plant realism (docs/parameters.md, "Plant realism"; sim.plantsim.PlantSim._integrate_real):
        # the gear's contact, sticking and the sliding direction decided at each sub-step's start
        mL_ = phys["m"] * phys["L"]
        mLg_ = mL_ * phys["g"]
        J_ = phys["I"] + phys["m"] * phys["L"] * phys["L"]
        play = rl.play if drive == "motor" else np.zeros(N, dtype=bool)
        delta = np.zeros(N)  # motor side minus wheel side of the gear play (m)
        stuck = rl.fric & (X[1] == 0.0)
        dirn = np.where(X[1] >= 0.0, 1.0, -1.0)
        eng = np.full(N, 2)
        v0 = np.zeros(N)
        shr = np.zeros(N)  # the share of the sub-step after a contact located in it (0: none)
        Mt_ = phys["M"] + phys["m"]

        def rhs_real(x: np.ndarray, duty: np.ndarray | None, us: np.ndarray, stk: np.ndarray,
                     ff: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            if duty is None:
                F = us
            else:
                Fg = _gate(force_from_duty(duty, x[1], motor_true), eng)
                F = np.where(shr > 0.0, shr * Fg, Fg)
            if accel_limit is not None:  # the drive's limit, as in the frictionless plant
                a0 = dynamics(0.0, x, zeros, phys)[1]
                a1 = dynamics(0.0, x, ones, phys)[1] - a0
                F = np.clip(F, (-accel_limit - a0) / a1, (accel_limit - a0) / a1)
            d = dynamics(0.0, x, np.where(rl.fric, F - ff, F), phys)
            d[1] = np.where(stk, 0.0, d[1])
            d[3] = np.where(stk, (mLg_ * np.sin(x[2])) / J_, d[3])
            return d, F

    sample = 0
    for k in range(n_ticks + 1):
        # --- sensors: this tick's reading enters the delay line, the delayed one comes out
        j = k % blk
        if j == 0:
            nblock = stream.take(min(blk, n_ticks + 1 - k))
        xe = X[0] if rl is None else np.where(play, X[0] + delta, X[0])  # the motor encoder
        ring_enc[k % L] = x_to_encoder(xe, sens, nblock[j, 0])
        ring_adc[k % L] = phi_to_adc(X[2], sens, nblock[j, 1])
        idx = ((k - d) % L) * N + cols
        seen_enc = flat_enc[idx]
        enc_total = enc_total + encoder_delta(seen_enc, enc_last)
        enc_last = seen_enc
        W[nz] = enc_total / cpm
        W[nz + 1] = adc_to_phi(flat_adc[idx], sens_fw)
        # --- controller (column by column: the same arithmetic for a run whatever the batch)
        out = _matmul_cols(G, W)
        us = np.clip(out[0], -u_max, u_max)
        duty = duty_from_force(us, out[1], motor_nom) if drive == "motor" else None
        if tr is not None:
            for name, val in (("x", X[0]), ("xdot", X[1]), ("phi", X[2]), ("phidot", X[3]), ("u_sat", us), ("x_meas", W[nz]), ("phi_meas", W[nz + 1])):
                tr[name][k] = val
            tr["duty"][k] = 0 if duty is None else duty
            if rl is None:
                tr["force"][k] = rhs(X, duty, us)[1]
            else:
                eng = _engagement(delta, rl.hp, play)
                shr = np.zeros(N)
                tr["force"][k] = rhs_real(X, duty, us, stuck, rl.fc * dirn)[1]
        W[:nz] = out[2:] + Bu_col * us
        if k == n_ticks:
            break
        # --- plant: RK4 sub-steps with the duty (or force) held
        if rl is not None:
            if duty is not None:
                mt = motor_true
                v0 = (bridge_fraction(duty, mt) * mt["V_supply"]) * mt["r_wheel"] / (mt["kt"] * mt["gear"])
            for _ in range(sub):
                eng = _engagement(delta, rl.hp, play)
                if duty is not None:
                    # a contact within the sub-step, located in it (PlantSim._contact_share)
                    shr = _contact_share(eng, delta, rl.hp, v0 - X[1], h, play)
                    eng = np.where(shr > 0.0, np.where(v0 - X[1] > 0.0, 1, -1), eng)
                F0 = rhs_real(X, duty, us, stuck, rl.fc * dirn)[1]
                sn, cs = np.sin(X[2]), np.cos(X[2])
                fext = (F0 + (mL_ * cs) * ((mLg_ * sn) / J_)) - mL_ * X[3] * X[3] * sn
                brk = stuck & (np.abs(fext) > rl.fs)
                slide = rl.fric & ~stuck & (X[1] != 0.0)
                dirn = np.where(brk, np.where(fext > 0.0, 1.0, -1.0), np.where(slide, np.where(X[1] > 0.0, 1.0, -1.0), dirn))
                stuck = stuck & ~brk
                ff = rl.fc * dirn
                k1, F = rhs_real(X, duty, us, stuck, ff)
                np.maximum(xdd_max, np.abs(k1[1]), out=xdd_max)
                np.maximum(f_max, np.abs(F), out=f_max)
                if sample >= w0:
                    phi_sq += X[2] * X[2]
                    f_sq += F * F
                k2 = rhs_real(X + (0.5 * h) * k1, duty, us, stuck, ff)[0]
                k3 = rhs_real(X + (0.5 * h) * k2, duty, us, stuck, ff)[0]
                k4 = rhs_real(X + h * k3, duty, us, stuck, ff)[0]
                Xn = X + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
                stop = rl.fric & ~stuck & (Xn[1] * dirn <= 0.0)  # stopped sliding: held by static friction
                if stop.any():
                    # ... unless the force at rest breaks it loose the other way at once (PlantSim._stop)
                    Fr = us if duty is None else _gate(force_from_duty(duty, np.zeros(N), motor_true), eng)
                    sn, cs = np.sin(Xn[2]), np.cos(Xn[2])
                    frest = (Fr + (mL_ * cs) * ((mLg_ * sn) / J_)) - mL_ * Xn[3] * Xn[3] * sn
                    rev = stop & (frest * dirn < 0.0) & (np.abs(frest) > rl.fs)
                    dv = X[1] - Xn[1]
                    ts = np.where(dv != 0.0, h * X[1] / np.where(dv != 0.0, dv, 1.0), h)
                    Xn[1] = np.where(rev, Xn[1] + 2.0 * rl.fc * dirn * (h - ts) / Mt_, np.where(stop, 0.0, Xn[1]))
                    dirn = np.where(rev, -dirn, dirn)
                    stop = stop & ~rev
                stuck = stuck | stop
                dl = (delta + h * v0) - (Xn[0] - X[0])
                delta = np.where(play, np.where(dl > rl.hp, rl.hp, np.where(dl < -rl.hp, -rl.hp, dl)), delta)
                X = Xn
                sample += 1
                aphi = np.abs(X[2])
                np.maximum(phi_max, aphi, out=phi_max)
                np.maximum(x_max, np.abs(X[0]), out=x_max)
                np.copyto(last_out, sample, where=aphi > settle_band)
            if s.progress is not None and k % 100 == 0:
                s.progress(k, n_ticks)
            continue
        for _ in range(sub):
            k1, F = rhs(X, duty, us)
            np.maximum(xdd_max, np.abs(k1[1]), out=xdd_max)
            np.maximum(f_max, np.abs(F), out=f_max)
            if sample >= w0:
                phi_sq += X[2] * X[2]
                f_sq += F * F
            k2 = rhs(X + (0.5 * h) * k1, duty, us)[0]
            k3 = rhs(X + (0.5 * h) * k2, duty, us)[0]
            k4 = rhs(X + h * k3, duty, us)[0]
            X = X + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
            sample += 1
            aphi = np.abs(X[2])
            np.maximum(phi_max, aphi, out=phi_max)
            np.maximum(x_max, np.abs(X[0]), out=x_max)
            np.copyto(last_out, sample, where=aphi > settle_band)
        if s.progress is not None and k % 100 == 0:
            s.progress(k, n_ticks)
    acc = {"phi_max": phi_max, "x_max": x_max, "xddot_max": xdd_max, "force_max": f_max, "last_out": last_out,
           "phi_sq": phi_sq, "f_sq": f_sq}
    return acc, tr


def _engagement(delta: np.ndarray, hp: np.ndarray, play: np.ndarray) -> np.ndarray:
    # the gear's contact: +1 the forward flank, -1 the backward one, 0 free in the play, 2 no play
    return np.where(play, np.where(delta >= hp, 1, np.where(delta <= -hp, -1, 0)), 2)


def _contact_share(eng: np.ndarray, delta: np.ndarray, hp: np.ndarray, rel: np.ndarray, h: float,
                   play: np.ndarray) -> np.ndarray:
    # sim.plantsim.PlantSim._contact_share per run, rel = the motor side's speed against the wheel side's
    safe = np.where(rel != 0.0, rel, 1.0)
    tc = np.where(rel > 0.0, (hp - delta) / safe, np.where(rel < 0.0, (-hp - delta) / safe, np.inf))
    return np.where(play & (eng == 0) & (tc < h), np.where(tc > 0.0, 1.0 - tc / h, 1.0), 0.0)


def _gate(F: np.ndarray, eng: np.ndarray) -> np.ndarray:
    # the motor force the gear passes: all of it without play, only a push into the flank in contact
    return np.where(eng == 2, F, np.where(eng == 1, np.where(F > 0.0, F, 0.0),
                                          np.where(eng == -1, np.where(F < 0.0, F, 0.0), 0.0)))


def _per_run(v: Any, n: int) -> np.ndarray:
    return np.ascontiguousarray(np.broadcast_to(np.asarray(v, dtype=float), (n,)))


def _loop_numba(s: _Setup, runs: RunSet) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray] | None]:
    """The compiled kernel (:mod:`sim.batch_kernel`), chunk of runs by chunk of runs."""
    import numba

    from . import batch_kernel as bk
    from .motor import _force_per_amp

    N, n_ticks = s.N, s.n_ticks
    T = n_ticks + 1
    ph, mt, mn = s.phys, s.motor_true, s.motor_nom
    # per-run constants with the reference's expressions (sim.plant.dynamics, sim.motor)
    M, m, L, I = (_per_run(ph[k], N) for k in ("M", "m", "L", "I"))
    Mm = M + m
    J = I + m * L * L
    mL = m * L
    b, g = _per_run(ph["b"], N), _per_run(ph["g"], N)
    fpa = _per_run(_force_per_amp(mt), N)
    Vs, R, kt, gear, rw = (_per_run(mt[k], N) for k in ("V_supply", "R", "kt", "gear", "r_wheel"))
    fpa_n = float(_force_per_amp(mn))
    sp, sf = s.sens_plant, s.sens_fw
    cpm_p, cpr_p = float(enc_counts_per_m(sp)), float(2.0 ** sp["adc_bits"] / sp["pot_range"])
    full_p = float(2 ** int(sp["adc_bits"]) - 1)
    rl = s.real
    if rl is not None:
        amp_a, inl_w = inl_terms(sp)
        rc = (_per_run(rl.fc, N), _per_run(rl.fs, N), _per_run(rl.hp, N), _per_run(mt["deadband"], N),
              _per_run(mt["duty_min"], N), _per_run(amp_a, N), float(inl_w))
    else:
        zr = np.zeros(N)
        rc = (zr, zr, zr, zr, zr, zr, 0.0)
    cpm_f, cpr_f = float(enc_counts_per_m(sf)), float(2.0 ** sf["adc_bits"] / sf["pot_range"])
    G = np.ascontiguousarray(s.Gs.transpose(0, 2, 1))  # (NG, nz+3, nz+2): a column contiguous
    Bu = np.ascontiguousarray(s.Bus.T)  # (nz, NG)
    u_max = np.ascontiguousarray(s.u_maxes, dtype=float)
    accel = s.accel_limit is not None
    al = float(s.accel_limit) if accel else 0.0
    model = s.noise
    fns = bk.draw_functions() if model.kind != "none" else None
    if model.kind == "none":
        nmode = bk.NOISE_NONE
    elif fns is not None:
        nmode = bk.NOISE_DRAW  # each run's generator drawn in the kernel, value for value
    else:  # numpy without the exported draw functions: drawn beforehand, chunk by chunk
        nmode = bk.NOISE_ARRAY
    draw_fn = fns[model.kind] if nmode == bk.NOISE_DRAW else 0
    hold = model.hold_ticks(s.Ts) if model.kind != "none" else 1
    # _NoiseStream's transform (uniform: off + scale * u, white: u * scale), then the channel mask
    n_affine = model.kind == "uniform"
    n_off, n_scl = _noise_scale(model, s.Ts)
    mask_x, mask_phi = (float(c in model.channels) for c in ("x", "phi"))
    acc = {k: np.zeros(N) for k in ("phi_max", "x_max", "xddot_max", "force_max", "phi_sq", "f_sq")}
    acc["last_out"] = np.zeros(N, dtype=np.int64)
    tr: dict[str, np.ndarray] | None = None
    trace = np.zeros((9, T, N)) if s.record else np.zeros((9, 1, 1))
    threads = bk.threads()
    chunk = KERNEL_CHUNK or kernel_chunk(N, threads, bk.LANES, nmode == bk.NOISE_ARRAY)
    chunk = max(1, min(chunk, N))
    no_noise = np.zeros((1, 1, 2))
    no_gens = np.zeros(1, dtype=np.int64)

    def prepare(z: slice) -> tuple[list[np.random.Generator], np.ndarray, np.ndarray]:
        # the chunk's noise source: the generators _NoiseStream would create (they must
        # live until the kernel returns), or the noise drawn beforehand
        if nmode == bk.NOISE_DRAW:
            gens = [np.random.default_rng(int(v)) for v in runs.noise_seed[z]]
            return gens, no_noise, np.array([bk.bitgen_address(gen) for gen in gens], dtype=np.int64)
        if nmode == bk.NOISE_ARRAY:
            return [], _NoiseStream(model, s.Ts, runs.noise_seed[z]).take_runs(T), no_gens  # (n, T, 2)
        return [], no_noise, no_gens

    def call(z: slice, noise_arr: np.ndarray, bitgens: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
        n = z.stop - z.start
        out = {k: np.zeros(n) for k in ("phi_max", "x_max", "xddot_max", "force_max", "phi_sq", "f_sq")}
        lo = np.zeros(n, dtype=np.int64)
        tr_c = np.zeros((9, T, n)) if s.record else trace
        # numba's thread count is per Python thread: this one may be the pipeline's worker
        numba.set_num_threads(threads)
        bk.run_chunk(
            n_ticks, s.sub, s.h, s.w0, s.settle_band,
            np.ascontiguousarray(runs.x0[z]), np.ascontiguousarray(runs.x_ref[z]),
            np.ascontiguousarray(runs.delay_ticks[z]),
            nmode, noise_arr, bitgens, draw_fn, hold, n_affine, n_off, n_scl, mask_x, mask_phi,
            Mm[z], J[z], mL[z], b[z], g[z],
            fpa[z], Vs[z], R[z], kt[z], gear[z], rw[z],
            s.drive == "motor", s.supply_measured, fpa_n,
            0.0 if s.supply_measured else float(mn["V_supply"]), float(mn["R"]), float(mn["kt"]), float(mn["gear"]),
            float(mn["r_wheel"]),
            cpm_p, cpr_p, float(sp["pot_offset"]), full_p, cpm_f, cpr_f, float(sf["pot_offset"]),
            G, Bu, u_max, np.ascontiguousarray(s.idx[z]),
            accel, al,
            out["phi_max"], out["x_max"], out["xddot_max"], out["force_max"], lo, out["phi_sq"], out["f_sq"],
            s.record, tr_c,
            rl is not None, *(a[z] for a in rc[:6]), rc[6],
        )
        return out, lo, tr_c

    def store(z: slice, res: tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]) -> None:
        out, lo, tr_c = res
        for k, v in out.items():
            acc[k][z] = v
        acc["last_out"][z] = lo
        if s.record:
            trace[:, :, z] = tr_c
        if s.progress is not None:
            s.progress(int(n_ticks * z.stop / N), n_ticks)

    chunks = [slice(a, min(a + chunk, N)) for a in range(0, N, chunk)]
    # a pipeline: the kernel runs a chunk in a worker thread (it releases the GIL) while this
    # thread creates the next chunk's generators (Python, ~30 us each)
    with ThreadPoolExecutor(max_workers=1) as pool:
        running: tuple[slice, Future, list[np.random.Generator]] | None = None
        for z in chunks:
            gens, noise_arr, bitgens = prepare(z)
            if running is not None:
                store(running[0], running[1].result())
            running = (z, pool.submit(call, z, noise_arr, bitgens), gens)
        if running is not None:
            store(running[0], running[1].result())
    if s.record:
        tr = {k: np.ascontiguousarray(trace[i]) for i, k in enumerate(_TRACES)}
        tr["t"] = np.arange(T) * s.Ts
    return acc, tr


def closed_loop_iosys(
    params: RobotParams,
    ctrl: Any,
    true: Mapping[str, float],
    delay_ticks: int,
    *,
    x_ref: float = 0.0,
    drive: str = "motor",
    plant_rate: float = 1000.0,
) -> "Any":
    """One run's closed loop as a python-control discrete-time ``nlsys`` (period ``Ts``).

    Scalar, written independently of :func:`simulate_batch` but with the same models:
    :class:`sim.sensors` conversions and a delay line of ``delay_ticks`` readings,
    ``ctrl.tick`` / ``ctrl.estimate`` of the float reference controller, the motor model
    and RK4 sub-steps of :func:`sim.plant.dynamics`.

    Parameters
    ----------
    params : RobotParams
        Nominal parameters (the firmware's).
    ctrl : DiscreteController
        Float reference controller.
    true : mapping
        The run's true ``M, m, L, I, b, g`` and motor constants.
    delay_ticks : int
        Measurement delay (ticks).
    x_ref : float
        Cart reference (m).
    drive : {"motor", "force"}
        As in :func:`simulate_batch`.
    plant_rate : float
        RK4 step rate (Hz).

    Returns
    -------
    control.NonlinearIOSystem
        Inputs ``n_x, n_phi`` (measurement noise, m and rad, per tick); states
        ``x, xdot, phi, phidot``, the controller state, the delay line and the encoder
        unwrapper; outputs = states.  Use :func:`closed_loop_x0` for the initial state.
    """
    import control as ct

    if drive not in ("motor", "force"):
        raise BatchError(f"drive must be 'motor' or 'force', got {drive!r}")
    Ts = float(ctrl.Ts)
    n = ctrl.Ac.shape[0]
    dl = int(delay_ticks)
    sub = max(1, math.ceil(Ts * plant_rate - 1e-9))
    h = Ts / sub
    phys = {k: float(true[k]) for k in PLANT_KEYS}
    mot = {k: float(true[k]) for k in MOTOR_KEYS}
    on = [k for k in REALISM_KEYS if float(true.get(k, 0.0)) != 0.0]
    if on:
        raise BatchError(f"closed_loop_iosys models the ideal robot; plant realism given: {', '.join(on)} "
                         f"(use simulate_batch)")
    cpm = float(enc_counts_per_m(params))

    def update(t: float, s: np.ndarray, w: np.ndarray, _p: Any) -> np.ndarray:
        x = s[:4]
        z = s[4 : 4 + n]
        line = s[4 + n : 4 + n + 2 * dl].reshape(dl, 2)
        enc_last, enc_total = s[-2], s[-1]
        reading = np.array([float(x_to_encoder(x[0], params, w[0])), float(phi_to_adc(x[2], params, w[1]))])
        if dl:
            seen = line[0].copy()
            line = np.vstack([line[1:], reading])
        else:
            seen = reading
        enc_total = enc_total + float(encoder_delta(int(seen[0]), int(enc_last)))
        v = [enc_total / cpm, float(adc_to_phi(seen[1], params)), x_ref]
        _, us, z_next = ctrl.tick(z, v)
        if drive == "motor":
            duty = float(duty_from_force(us, ctrl.estimate(z, v)[1], params))

            def f(xx: np.ndarray, dd: float) -> np.ndarray:
                return dynamics(0.0, xx, np.array([float(force_from_duty(dd, xx[1], mot))]), phys)

            hold = duty
        else:

            def f(xx: np.ndarray, uu: float) -> np.ndarray:
                return dynamics(0.0, xx, np.array([uu]), phys)

            hold = us
        for _ in range(sub):
            x = rk4_step(f, x, hold, h)
        return np.concatenate([x, z_next, line.ravel(), [seen[0], enc_total]])

    nstates = 4 + n + 2 * dl + 2
    return ct.nlsys(update, None, inputs=["n_x", "n_phi"], states=nstates, dt=Ts, name="closed_loop")


def closed_loop_x0(params: RobotParams, ctrl: Any, x0: np.ndarray, delay_ticks: int) -> np.ndarray:
    """Initial state of :func:`closed_loop_iosys`: plant ``x0``, zero controller state,
    the delay line filled with the noiseless reading of ``x0``."""
    x0 = np.asarray(x0, dtype=float)
    r0 = [float(x_to_encoder(x0[0], params)), float(phi_to_adc(x0[2], params))]
    enc0 = float(encoder_delta(int(r0[0]), 0))
    return np.concatenate([x0, np.zeros(ctrl.Ac.shape[0]), np.tile(r0, int(delay_ticks)), [r0[0], enc0]])


def simulate_run(
    params: RobotParams,
    ctrl: Any,
    runs: RunSet,
    i: int,
    *,
    duration: float = 5.0,
    noise: NoiseModel | None = None,
    drive: str = "motor",
    plant_rate: float = 1000.0,
) -> dict[str, np.ndarray]:
    """Run ``i`` of ``runs`` alone, with ``control.input_output_response``.

    The noise is drawn tick by tick with a single-run :class:`sim.sensors.NoiseSource`
    seeded like the batch run.

    Returns
    -------
    dict
        ``t`` and ``x, xdot, phi, phidot`` at every tick (``duration * rate + 1`` samples).
    """
    import control as ct

    from .sensors import NoiseSource

    noise = NoiseModel() if noise is None else noise
    Ts = float(ctrl.Ts)
    n_ticks = int(round(duration / Ts))
    src = NoiseSource(noise, Ts, np.random.default_rng(int(runs.noise_seed[i])))
    W = np.stack([src.draw().copy() for _ in range(n_ticks + 1)], axis=1)  # (2, T)
    d = int(runs.delay_ticks[i])
    sys = closed_loop_iosys(params, ctrl, runs.true_params(params, i), d, x_ref=float(runs.x_ref[i]), drive=drive, plant_rate=plant_rate)
    T = np.arange(n_ticks + 1) * Ts
    resp = ct.input_output_response(sys, T, W, closed_loop_x0(params, ctrl, runs.x0[i], d))
    S = np.asarray(resp.states)
    return {"t": T, "x": S[0], "xdot": S[1], "phi": S[2], "phidot": S[3]}
