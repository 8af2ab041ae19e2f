"""Discrete-time controller at the loop rate: what the firmware runs.

The continuous plant (:func:`sim.plant.linear_model`) is discretised with a zero-order
hold at the loop period ``Ts = 1/params.rate``.  The measurements ``[x, phi]`` arrive
``d = round(params.delay / Ts)`` ticks late (10 ms at 500 Hz: d = 5).

Structure (documented in ``docs/firmware.md``; the firmware implements exactly this):

* **filter** (current estimator of the *delayed* state): at tick ``k`` the measurement
  ``y[k] = C x[k-d]`` corrects the a-priori estimate ``p`` of ``x[k-d]``::

      xf = p + M (y - C p)

* **predictor** (Smith-predictor-like, instead of 4*d augmented states): the stored
  inputs ``b_i = u[k-d+i]`` (i = 0..d-1) carry ``xf`` forward to the current tick::

      xh = Ad^d xf + sum_i Ad^(d-1-i) Bd b_i

* **state feedback** with reference precompensation for the cart position::

      u = -K xh + kr x_ref          (then saturated to +-u_max: u_sat)

* **update**: ``p <- Ad xf + Bd b_0`` (a-priori estimate of ``x[k-d+1]``), and the input
  buffer shifts by one with the *saturated* input ``u_sat`` entering at the end.

The controller state ``z = [p (4), b_0 .. b_{d-1}]`` has ``4 + d`` entries and the whole
thing is linear: ``u = Cc z + Dc v`` and ``z' = Ac z + Bc v + Bu u_sat`` with
``v = [x_meas, phi_meas, x_ref]``.  The predictor costs d stored inputs (5 numbers) where
the augmented-state design would need 4*d extra estimator states; both give the same
input-output behaviour for a delay that is a whole number of ticks.

K comes from ``dlqr`` with the continuous weights mapped as ``Qd = Q Ts``, ``Rd = R Ts``;
the discrete closed-loop poles equal ``exp(s Ts)`` of the continuous ones to 2e-5 (measured
2.2e-6 for the shipped design, 1.3e-5 for the report's weights;
``tests/test_discrete_loop.py::test_dlqr_poles_match_the_continuous_design``).  M is
the steady-state Kalman filter gain for a force disturbance plus small accelerations as
process noise and the sensor noise below.

**The shipped design** (``Q_DEFAULT``, ``R_DEFAULT``, ``OBSERVER_DEFAULT``,
``A_CMD_DEFAULT``) is not the report's.  The report's weights (``Q_REPORT = diag(5.4, 0, 0.8,
0)``, ``R_REPORT = 0.001``, which reproduce its continuous K) ask up to ~14 N of the drive and
accelerate the cart at 22-24 m/s^2 on a 0.1 rad tilt or a 20 cm step, far past the report's
own 5 m/s^2 limit.  The default clamps the force command at ``A_CMD_DEFAULT / B[1]`` -- the
force that accelerates the cart at 4.73 m/s^2 from upright (``1/B[1]`` is the cart's effective
mass with the pendulum free to swing) -- and uses ``Q = diag(1.994, 0, 0.4917, 0.00182)``,
``R = 0.01`` and an estimator designed for the sensor noise divided by 4 (``OBSERVER_DEFAULT =
0.25``: it trusts the model more than the sensors).  It is the best design of the robust search
(``upright design --robust``, :mod:`host.design.robust_search`; ``docs/parameters.md``, Robust
design): no design met every constraint over the whole uncertainty set; among those that meet
every report scenario on the nominal robot and that the fixed-point table carries precisely
(``host.design.robust.FORCE_LSB_MAX``), this one loses the pendulum at the fewest robots of the
set (38 of 161, against 75 for the previous default, ``Q = diag(1.5, 0, 0.1, 0.02)``, observer 1,
clamp 4.4 m/s^2; most of them to the 1 N s kick on a weak drive).

The estimator is designed for the sensors' noise.  The default ``SIGMA_MEAS`` is about
one encoder count and two ADC counts; a scenario that puts more measurement noise on the
sensors gets a filter designed for that noise (:func:`controller_for`), as one would
retune the filter for noisier sensors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Sequence

import control as ct
import numpy as np
import scipy.linalg as sl

from sim.params import RobotParams

if TYPE_CHECKING:
    from sim.scenario import Scenario
from sim.plant import dynamics, linear_model, rk4_step

__all__ = [
    "DiscreteController",
    "controller_ss",
    "assemble",
    "discretise",
    "delay_steps",
    "force_limit",
    "simulate_loop",
    "delayed_plant",
    "closed_loop_poles",
    "controller_for",
    "force_clamp",
    "sigma_meas_for",
    "Q_DEFAULT",
    "R_DEFAULT",
    "A_CMD_DEFAULT",
    "OBSERVER_DEFAULT",
    "Q_REPORT",
    "R_REPORT",
]

Q_REPORT = (5.4, 0.0, 0.8, 0.0)
R_REPORT = 0.001
"""The report's LQR weights (they reproduce its continuous K to 1e-5)."""
Q_DEFAULT = (1.994, 0.0, 0.4917, 0.00182)
R_DEFAULT = 0.01
A_CMD_DEFAULT = 4.73  # m/s^2: the cart acceleration the force clamp allows from upright
OBSERVER_DEFAULT = 0.25  # the Kalman filter is designed for SIGMA_MEAS / OBSERVER_DEFAULT (< 1: trusts the model more)
"""The shipped design: weights, commanded-acceleration limit and estimator speed (module docstring)."""
# Kalman design noise (standard deviations)
SIGMA_FORCE = 1.0  # N, force disturbance at the cart
SIGMA_ACC = (0.1, 0.3)  # m/s^2 and rad/s^2, unmodelled accelerations of x and phi
SIGMA_MEAS = (2e-4, 2e-3)  # m and rad: about one encoder count and two ADC counts


def force_limit(params: RobotParams) -> float:
    """Largest cart force the drive can produce (N): the stall force at full supply.

    ``F = n_motors * gear * kt * (V_supply / R) / r_wheel``: full duty at zero speed.
    """
    return params.n_motors * params.gear * params.kt * params.V_supply / (params.R * params.r_wheel)


def force_clamp(params: RobotParams, a_cmd: float = A_CMD_DEFAULT) -> float:
    """Force command limit (N) that accelerates the cart at ``a_cmd`` from upright.

    ``a_cmd / B[1]`` with ``B`` of the linearised plant: ``1/B[1] = q / (I + m L^2)`` is the
    cart's effective mass when the pendulum is free to swing (0.608 kg for the report's
    robot, against M + m = 0.716 kg).
    """
    if not a_cmd > 0:
        raise ValueError(f"a_cmd must be > 0, got {a_cmd}")
    _, B, _, _ = linear_model(params)
    return float(a_cmd / B[1, 0])


def sigma_meas_for(scenario: "Scenario", params: RobotParams) -> tuple[float, float]:
    """Kalman measurement noise ``(x in m, phi in rad)`` for a scenario's sensor noise.

    The standard deviation of the scenario's measurement noise on each channel
    (:meth:`sim.sensors.NoiseModel.std` at the loop period), or the default ``SIGMA_MEAS``
    where that is larger (quantisation stays).
    """
    n = scenario.noise
    sig = list(SIGMA_MEAS)
    s = n.std(1.0 / scenario.apply(params).rate)  # 0 without noise
    for i, ch in enumerate(("x", "phi")):
        if ch in n.channels:
            sig[i] = max(sig[i], s)
    return (sig[0], sig[1])


def controller_for(scenario: "Scenario", params: RobotParams, **kwargs: object) -> "DiscreteController":
    """The shipped design for a scenario: :func:`controller_ss` with the estimator matched to
    the scenario's measurement noise (:func:`sigma_meas_for`).

    ``params`` are the design parameters (the scenario's plant overrides are not applied to
    the design: the firmware does not know them); other keyword arguments go to
    :func:`controller_ss`.
    """
    kwargs.setdefault("sigma_meas", sigma_meas_for(scenario, params))
    return controller_ss(params, **kwargs)  # type: ignore[arg-type]


def delay_steps(params: RobotParams, rate: float | None = None, delay: float | None = None) -> int:
    """Measurement delay in whole loop ticks (rounded)."""
    rate = float(params.rate if rate is None else rate)
    delay = float(params.delay if delay is None else delay)
    if rate <= 0 or delay < 0:
        raise ValueError(f"rate must be > 0 and delay >= 0, got rate={rate}, delay={delay}")
    return int(round(delay * rate))


def discretise(params: RobotParams, rate: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """ZOH discretisation of the linear plant at the loop rate.

    Returns
    -------
    Ad : ndarray (4, 4)
    Bd : ndarray (4, 1)
    C : ndarray (2, 4)
        Measures x and phi.
    Ts : float
        Sample period (s).
    """
    rate = float(params.rate if rate is None else rate)
    if rate <= 0:
        raise ValueError(f"rate must be > 0, got {rate}")
    Ts = 1.0 / rate
    A, B, C, _ = linear_model(params)
    n = A.shape[0]
    big = np.zeros((n + 1, n + 1))
    big[:n, :n] = A
    big[:n, n:] = B
    e = sl.expm(big * Ts)
    return e[:n, :n], e[:n, n:], C, Ts


@dataclass
class DiscreteController:
    """The complete linear discrete-time controller the firmware runs.

    At tick ``k`` with ``v[k] = [x_meas (m), phi_meas (rad), x_ref (m)]`` (the
    measurements available at that tick, i.e. ``delay_steps`` ticks old)::

        u[k]   = Cc z[k] + Dc v[k]                     # force (N), before saturation
        u_sat  = clip(u[k], -u_max, u_max)
        z[k+1] = Ac z[k] + Bc v[k] + Bu u_sat          # the *saturated* u is fed back

    :meth:`output` and :meth:`step` implement exactly this; the fixed-point firmware and
    the batch simulator implement the same.  The structured pieces (``Ad, Bd, C, K, M,
    kr``, ``Kf = K Ad^d`` and ``kb_i = K Ad^(d-1-i) Bd``) are kept for the fixed-point
    export: ``u = -Kf xf - kb . b + kr x_ref`` with ``xf = p + M (y - C p)``.

    Attributes
    ----------
    Ac, Bc, Cc, Dc, Bu : ndarray
        Shapes (n, n), (n, 3), (1, n), (1, 3), (n, 1) with ``n = 4 + delay_steps``.
    Ts : float
        Sample period (s).
    delay_steps : int
        Measurement delay in ticks.
    u_max : float
        Force saturation (N).
    """

    Ac: np.ndarray
    Bc: np.ndarray
    Cc: np.ndarray
    Dc: np.ndarray
    Bu: np.ndarray
    Ts: float
    delay_steps: int
    u_max: float
    Ad: np.ndarray = field(repr=False)
    Bd: np.ndarray = field(repr=False)
    C: np.ndarray = field(repr=False)
    K: np.ndarray = field(repr=False)
    M: np.ndarray = field(repr=False)
    kr: float = 0.0
    Kf: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]
    kb: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]
    design: str = "lqr"

    @property
    def n(self) -> int:
        """Number of controller states (4 + delay_steps)."""
        return self.Ac.shape[0]

    def initial_state(self, v: Sequence[float] | None = None) -> np.ndarray:
        """Start state: at rest, empty input buffer; upright at 0 unless measurements ``v``.

        With ``v = [x_meas, phi_meas, ...]`` the estimate starts at the measured position
        and tilt, as the firmware does when balancing starts.
        """
        z = np.zeros(self.n)
        if v is not None:
            z[0], z[2] = float(v[0]), float(v[1])
        return z

    def output(self, z: np.ndarray, v: Sequence[float]) -> float:
        """Unsaturated force command ``u = Cc z + Dc v`` (N)."""
        return float((self.Cc @ z + self.Dc @ np.asarray(v, dtype=float))[0])

    def saturate(self, u: float) -> float:
        """Clip a force to ``[-u_max, u_max]``."""
        return min(max(u, -self.u_max), self.u_max)

    def step(self, z: np.ndarray, v: Sequence[float], u_sat: float) -> np.ndarray:
        """Next state ``z' = Ac z + Bc v + Bu u_sat``."""
        return self.Ac @ z + self.Bc @ np.asarray(v, dtype=float) + self.Bu[:, 0] * u_sat

    def estimate(self, z: np.ndarray, v: Sequence[float]) -> np.ndarray:
        """Predicted current state ``xh = Ad^d xf + sum Ad^(d-1-i) Bd b_i``."""
        d = self.delay_steps
        y = np.asarray(v[:2], dtype=float)
        p = z[:4]
        xf = p + self.M @ (y - self.C @ p)
        xh = np.linalg.matrix_power(self.Ad, d) @ xf
        for i in range(d):
            xh = xh + (np.linalg.matrix_power(self.Ad, d - 1 - i) @ self.Bd)[:, 0] * z[4 + i]
        return xh

    def tick(self, z: np.ndarray, v: Sequence[float]) -> tuple[float, float, np.ndarray]:
        """One controller tick: ``(u, u_sat, z_next)``."""
        u = self.output(z, v)
        us = self.saturate(u)
        return u, us, self.step(z, v, us)


def _kalman_gain(Ad: np.ndarray, Bd: np.ndarray, C: np.ndarray, Ts: float, sigma_force: float,
                 sigma_acc: Sequence[float], sigma_meas: Sequence[float]) -> np.ndarray:
    Qn = (sigma_force**2) * (Bd @ Bd.T) + np.diag([0.0, (sigma_acc[0] * Ts) ** 2, 0.0, (sigma_acc[1] * Ts) ** 2])
    Rn = np.diag(np.square(sigma_meas))
    P = sl.solve_discrete_are(Ad.T, C.T, Qn, Rn)
    return P @ C.T @ np.linalg.inv(C @ P @ C.T + Rn)


def controller_ss(
    params: RobotParams,
    rate: float | None = None,
    delay: float | None = None,
    design: str = "lqr",
    *,
    Q: Sequence[float] | None = None,
    R: float | None = None,
    K: Sequence[float] | None = None,
    poles: Sequence[complex] | None = None,
    u_max: float | None = None,
    sigma_force: float = SIGMA_FORCE,
    sigma_acc: Sequence[float] = SIGMA_ACC,
    sigma_meas: Sequence[float] = SIGMA_MEAS,
    observer: float | None = None,
) -> DiscreteController:
    """Design the discrete controller (observer + predictor + state feedback + kr).

    Parameters
    ----------
    params : RobotParams
        Robot parameters.
    rate : float, optional
        Loop rate in Hz (default ``params.rate``).
    delay : float, optional
        Measurement delay in s (default ``params.delay``); rounded to whole ticks.
    design : {"lqr", "place", "gain"}
        ``"lqr"``: dlqr with continuous weights ``Q`` (diagonal), ``R`` mapped as
        ``Q Ts``, ``R Ts``.  ``"place"``: discrete pole placement at ``exp(s Ts)`` of the
        continuous ``poles`` (default: the report's).  ``"gain"``: use the given
        state-feedback row ``K``.
    Q : sequence of 4 float, optional
        Diagonal of the continuous state weight (default ``Q_DEFAULT``).
    R : float, optional
        Continuous input weight (default ``R_DEFAULT``).
    K : sequence of 4 float, optional
        State feedback for ``design="gain"`` (``u = -K x``).
    poles : sequence of 4 complex, optional
        Continuous closed-loop poles for ``design="place"``.
    u_max : float, optional
        Force saturation (N); default :func:`force_clamp` (``A_CMD_DEFAULT`` from upright).
    sigma_force, sigma_acc, sigma_meas
        Kalman design noise: force disturbance (N), accelerations of x and phi,
        measurement noise of the sensors, x (m) and phi (rad).
    observer : float, optional
        Estimator speed: the filter is designed for the measurement noise ``sigma_meas /
        observer`` (> 1 trusts the sensors more, a faster estimator); default
        ``OBSERVER_DEFAULT``, the shipped design's.

    Returns
    -------
    DiscreteController

    Raises
    ------
    ValueError
        On an unknown design, bad weights or a non-stabilising gain.
    """
    Ad, Bd, C, Ts = discretise(params, rate)
    d = delay_steps(params, rate, delay)
    if poles is not None and design != "place":
        raise ValueError("poles are only used with design='place'")
    if design == "lqr":
        if K is not None:
            raise ValueError("K is only used with design='gain'")
        q = np.asarray(Q_DEFAULT if Q is None else Q, dtype=float)
        r = float(R_DEFAULT if R is None else R)
        if q.shape != (4,) or np.any(q < 0) or r <= 0:
            raise ValueError(f"Q must be 4 non-negative weights and R > 0, got Q={q}, R={r}")
        Kd, _, _ = ct.dlqr(Ad, Bd, np.diag(q) * Ts, np.array([[r * Ts]]))
        Kd = np.asarray(Kd, dtype=float).reshape(1, 4)
    elif design == "place":
        if Q is not None or R is not None:
            raise ValueError("design='place' takes poles (or the report's), not Q/R")
        from host.design.controllers import REPORT_PLACE_POLES

        sp = np.asarray(REPORT_PLACE_POLES if poles is None else poles, dtype=complex)
        if sp.shape != (4,) or np.any(sp.real >= 0):
            raise ValueError(f"place needs 4 stable continuous poles, got {poles!r}")
        Kd = np.asarray(ct.place(Ad, Bd, np.exp(sp * Ts)), dtype=float).reshape(1, 4)
    elif design == "gain":
        if K is None or Q is not None or R is not None:
            raise ValueError("design='gain' takes K (and no Q/R)")
        Kd = np.asarray(K, dtype=float).reshape(1, 4)
    else:
        raise ValueError(f"unknown design {design!r} (expected 'lqr', 'place' or 'gain')")
    if np.max(np.abs(np.linalg.eigvals(Ad - Bd @ Kd))) >= 1.0:
        raise ValueError("the state feedback does not stabilise the discrete plant")
    obs = OBSERVER_DEFAULT if observer is None else float(observer)
    if not (math.isfinite(obs) and obs > 0):
        raise ValueError(f"observer must be > 0, got {observer!r}")
    M = _kalman_gain(Ad, Bd, C, Ts, sigma_force, sigma_acc, tuple(float(v) / obs for v in sigma_meas))
    # reference precompensator: unit DC gain from x_ref to x with u = -K x + kr r
    cx = np.array([[1.0, 0.0, 0.0, 0.0]])
    kr = float(1.0 / (cx @ np.linalg.solve(np.eye(4) - Ad + Bd @ Kd, Bd))[0, 0])
    umax = force_clamp(params) if u_max is None else float(u_max)
    if not umax > 0:
        raise ValueError(f"u_max must be > 0, got {umax}")

    return assemble(Ad, Bd, C, Ts, d, Kd, M, kr, umax, design)


def assemble(Ad: np.ndarray, Bd: np.ndarray, C: np.ndarray, Ts: float, d: int, Kd: np.ndarray, M: np.ndarray,
             kr: float, umax: float, design: str) -> DiscreteController:
    """The firmware's controller structure (module docstring) from its pieces.

    Filter gain ``M`` (4, 2) on the delayed measurement, predictor over ``d`` stored forces,
    state feedback ``Kd`` (1, 4), precompensator ``kr``, clamp ``umax``.  Used by
    :func:`controller_ss` (``M`` the Kalman gain) and by the reduced-order observer's firmware
    form (:meth:`host.design.reduced.ReducedOrderController.firmware_form`).
    """
    Kd = np.asarray(Kd, dtype=float).reshape(1, 4)
    M = np.asarray(M, dtype=float).reshape(4, 2)
    Phi = np.linalg.matrix_power(Ad, d)
    Kf = Kd @ Phi  # (1, 4)
    kb = np.array([(Kd @ np.linalg.matrix_power(Ad, d - 1 - i) @ Bd)[0, 0] for i in range(d)])
    n = 4 + d
    I_MC = np.eye(4) - M @ C
    Ac = np.zeros((n, n))
    Bc = np.zeros((n, 3))
    Bu = np.zeros((n, 1))
    Cc = np.zeros((1, n))
    Dc = np.zeros((1, 3))
    Ac[:4, :4] = Ad @ I_MC
    Bc[:4, :2] = Ad @ M
    Cc[0, :4] = -(Kf @ I_MC)[0]
    Cc[0, 4:] = -kb
    Dc[0, :2] = -(Kf @ M)[0]
    Dc[0, 2] = kr
    if d == 0:
        Bu[:4, 0] = Bd[:, 0]
    else:
        Ac[:4, 4] = Bd[:, 0]
        for i in range(d - 1):
            Ac[4 + i, 5 + i] = 1.0
        Bu[n - 1, 0] = 1.0
    return DiscreteController(
        Ac=Ac, Bc=Bc, Cc=Cc, Dc=Dc, Bu=Bu, Ts=Ts, delay_steps=d, u_max=umax,
        Ad=Ad, Bd=Bd, C=C, K=Kd, M=M, kr=kr, Kf=Kf, kb=kb, design=design,
    )


def delayed_plant(params: RobotParams, rate: float | None = None,
                  delay: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, int]:
    """The discrete plant with the measurement delay as extra states.

    State ``[x (4), y[k-1], ..., y[k-d]]`` (``y = [x, phi]``, 2 per delayed sample); the
    output is the oldest sample ``y[k-d]``, which is what the controller sees at tick k.

    Returns
    -------
    A : ndarray (4 + 2d, 4 + 2d)
    B : ndarray (4 + 2d, 1)
    C : ndarray (2, 4 + 2d)
    Ts : float
    d : int
    """
    Ad, Bd, C, Ts = discretise(params, rate)
    d = delay_steps(params, rate, delay)
    n = 4 + 2 * d
    A = np.zeros((n, n))
    A[:4, :4] = Ad
    B = np.zeros((n, 1))
    B[:4] = Bd
    Cd = np.zeros((2, n))
    if d == 0:
        Cd[:, :4] = C
        return A, B, Cd, Ts, d
    A[4:6, :4] = C  # y[k] enters the delay line
    for i in range(1, d):
        A[4 + 2 * i : 6 + 2 * i, 2 + 2 * i : 4 + 2 * i] = np.eye(2)
    Cd[:, n - 2 :] = np.eye(2)
    return A, B, Cd, Ts, d


def closed_loop_poles(params: RobotParams, ctrl: DiscreteController) -> np.ndarray:
    """Eigenvalues of the linear loop: delayed plant and controller (no saturation).

    With the exact predictor they are the state-feedback poles ``eig(Ad - Bd K)``, the
    filter poles ``eig(Ad (I - M C))`` and zeros (pure delays).
    """
    A, B, C, _, d = delayed_plant(params, 1.0 / ctrl.Ts, ctrl.delay_steps * ctrl.Ts)
    n, m = A.shape[0], ctrl.n
    # v = [y, r] with r = 0; u = Cc z + Dc[:, :2] C xp
    Dy = ctrl.Dc[:, :2]
    Acl = np.zeros((n + m, n + m))
    Acl[:n, :n] = A + B @ Dy @ C
    Acl[:n, n:] = B @ ctrl.Cc
    Acl[n:, :n] = ctrl.Bc[:, :2] @ C + ctrl.Bu @ Dy @ C
    Acl[n:, n:] = ctrl.Ac + ctrl.Bu @ ctrl.Cc
    return np.linalg.eigvals(Acl)


def simulate_loop(
    params: RobotParams,
    ctrl: DiscreteController,
    x0: Sequence[float],
    duration: float,
    *,
    x_ref: Callable[[float], float] | float = 0.0,
    controller: Callable[[int, float, float, float], float] | None = None,
    quantise: bool = False,
    substeps: int = 2,
    disturbance: Callable[[float], float] | None = None,
    start_from_measurement: bool = False,
) -> dict[str, np.ndarray]:
    """Close the nonlinear plant around a discrete controller, with delay and saturation.

    Each tick ``k`` (period ``ctrl.Ts``) the controller sees the state of ``delay_steps``
    ticks earlier (``x0`` before the start), computes a force, which is saturated and
    held over the tick (RK4, ``substeps`` per tick).

    Parameters
    ----------
    params : RobotParams
        Plant parameters.
    ctrl : DiscreteController
        The float reference controller (used unless ``controller`` is given).
    x0 : sequence of 4 float
        Initial plant state.
    duration : float
        Simulated time (s).
    x_ref : float or callable
        Cart position reference (m), constant or ``x_ref(t)``.
    controller : callable, optional
        ``controller(k, x_meas, phi_meas, x_ref) -> u_sat`` replacing the float one
        (e.g. the fixed-point firmware); it must saturate itself.
    quantise : bool
        Quantise the measurements like the sensors (encoder counts, ADC counts).
    substeps : int
        RK4 steps per tick.
    disturbance : callable, optional
        Extra force ``disturbance(t)`` (N) at the cart.
    start_from_measurement : bool
        Start the float controller's estimate at the first measurement (as the firmware
        does when balancing starts) instead of at zero.

    Returns
    -------
    dict
        Arrays ``t, x, xdot, phi, phidot, u, xddot, x_meas, phi_meas, x_ref``.
    """
    n = int(round(duration / ctrl.Ts))
    d = ctrl.delay_steps
    Ts = ctrl.Ts
    phys = params.physical
    x = np.asarray(x0, dtype=float).copy()
    hist = [x.copy()] * (d + 1)
    z = ctrl.initial_state()
    cols = {k: np.zeros(n) for k in ("t", "x", "xdot", "phi", "phidot", "u", "xddot", "x_meas", "phi_meas", "x_ref")}
    m_per_count = 2 * math.pi * params.r_wheel / params.enc_cpr
    rad_per_count = params.pot_range / 2**params.adc_bits

    def f(xx: np.ndarray, uu: float) -> np.ndarray:
        return dynamics(0.0, xx, np.array([uu]), phys)

    for k in range(n):
        t = k * Ts
        xm = hist[0]
        ym, phm = float(xm[0]), float(xm[2])
        if quantise:
            ym = round(ym / m_per_count) * m_per_count
            phm = round(phm / rad_per_count) * rad_per_count
        r = float(x_ref(t)) if callable(x_ref) else float(x_ref)
        if k == 0 and start_from_measurement:
            z = ctrl.initial_state([ym, phm])
        if controller is None:
            _, us, z = ctrl.tick(z, [ym, phm, r])
        else:
            us = float(controller(k, ym, phm, r))
        F = us + (float(disturbance(t)) if disturbance is not None else 0.0)
        cols["t"][k] = t
        for j, name in enumerate(("x", "xdot", "phi", "phidot")):
            cols[name][k] = x[j]
        cols["u"][k] = us
        cols["xddot"][k] = f(x, F)[1]
        cols["x_meas"][k] = ym
        cols["phi_meas"][k] = phm
        cols["x_ref"][k] = r
        for _ in range(substeps):
            x = rk4_step(f, x, F, Ts / substeps)
        hist = hist[1:] + [x.copy()]
    return cols
