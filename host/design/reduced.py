"""The reduced-order observer (the report's section 2.3.d future work): design and discretisation.

The sensors measure two of the four states, ``y = [x, phi]``; a reduced-order (Luenberger,
Gopinath) observer estimates only the other two, ``w = [xdot, phidot]``, and takes ``x`` and
``phi`` straight from the sensors.  With the states split as ``x = Sy y + Sw w``::

    ydot = A11 y + A12 w + B1 u          w' = A21 y + A22 w + B2 u

the observer state ``z = w_hat - Lr y`` obeys::

    zdot = F z + G y + H u,   F = A22 - Lr A12,  G = F Lr + A21 - Lr A11,  H = B2 - Lr B1

and ``w_hat = z + Lr y``.  ``Lr`` places the two poles of ``F`` (:func:`reduced_observer`).
The same equations in discrete time with ``Ad, Bd`` (ZOH at ``Ts``) give the discrete
observer, its poles placed at ``exp(s Ts)`` of the continuous ones
(:func:`discrete_reduced_observer`).

**With the measurement delay** of ``d`` ticks the observer runs on the delayed time axis,
exactly as the full estimator of :mod:`host.design.discrete` does: at tick ``k`` it has
``y[k] = C x[k-d]`` and estimates ``x[k-d]``; the stored inputs ``b_i = u[k-d+i]`` carry it
forward (``xh = Ad^d xf + sum_i Ad^(d-1-i) Bd b_i``) to the state feedback ``u = -K xh + kr r``.
:func:`reduced_controller` returns the whole thing as a :class:`host.design.discrete.DiscreteController`
(controller state ``[z (2), b_0 .. b_{d-1}]``: ``2 + d`` numbers against ``4 + d`` for the full
estimator), so :func:`host.design.discrete.simulate_loop` and
:func:`host.design.discrete.closed_loop_poles` work on it unchanged.  Its closed-loop poles
are those of ``Ad - Bd K`` and of ``F`` (separation), plus zeros for the delay line.

**In the firmware** a gain table says which estimator it carries (``EST``,
:mod:`host.design.export`): :func:`host.design.export.export` of a
:class:`ReducedOrderController` writes the observer in the firmware's predictor-corrector form
(:func:`host.design.export.filter_gain`), which is this observer exactly.
:func:`reduced_for` builds it from a full-estimator controller (same state feedback, rate,
delay and force clamp), with :data:`REDUCED_POLES_DEFAULT` unless told otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import control as ct
import numpy as np

from host.design.discrete import DiscreteController, delay_steps, discretise
from sim.params import RobotParams
from sim.plant import linear_model

__all__ = ["MEASURED", "UNMEASURED", "REDUCED_POLES_DEFAULT", "ReducedObserver", "reduced_observer",
           "discrete_reduced_observer", "ReducedOrderController", "reduced_controller", "reduced_for",
           "back_emf_gain", "noise_response"]

REDUCED_POLES_DEFAULT = (-4.0, -5.0)
"""Continuous observer poles (rad/s) of the exported reduced-order table (``upright export
--estimator reduced``).  Chosen in HIL (firmware on the unix port, lockstep) on the report's
scenarios with the shipped state feedback and force clamp: faster poles pass more of the
sensors' noise and counts into the speed estimates -- the report's uniform 5 mm / 5 mrad noise
then breaks the 5 m/s^2 acceleration limit (peak 3.5 m/s^2 at -4/-5, 4.2 at -5/-6, 4.8 at -6/-7,
5.5 at -7/-8) -- and at -5/-6 the kick's tilt settles in a one-count limit cycle past the band
(3.12 s); -4/-5 meets every constraint the full estimator meets there except under the report's
white noise.  No poles meet that noise (0.07 rad rms on the angle, 71 mm on the position, per
tick): :func:`noise_response` of the linear loop (which agrees with the float simulator within
1-8 %) gives 20.9 N rms of force at -4/-5 and at best 4.85 N over a sweep of pole pairs from -0.5
to -80 rad/s (4.62 N with all four entries of ``Lr`` optimised), against the 2.88 N clamp and the
full estimator's 0.68 N: the measured ``x, phi`` go straight into ``-K x`` and the differentiated
position into the speed estimate, which the back-EMF compensation multiplies by
:func:`back_emf_gain` (44 N s/m); with an ideal compensation the optimised ``Lr`` still asks
4.09 N.  It needs the full estimator's filtering of ``x`` and ``phi``."""

MEASURED = (0, 2)
"""State indices the sensors give: x, phi."""
UNMEASURED = (1, 3)
"""State indices the reduced observer estimates: xdot, phidot."""


@dataclass(frozen=True)
class ReducedObserver:
    """A reduced-order observer ``z' = F z + G y + H u``, ``w_hat = z + Lr y``.

    Continuous (``Ts = 0``: ``z'`` is ``dz/dt``) or discrete (``Ts > 0``: ``z'`` is ``z[k+1]``).

    Attributes
    ----------
    F : ndarray (2, 2)
    G : ndarray (2, 2)
    H : ndarray (2, 1)
    Lr : ndarray (2, 2)
    poles : ndarray
        Eigenvalues of ``F`` (s-plane if continuous, z-plane if discrete).
    Sy, Sw : ndarray (4, 2)
        ``x = Sy y + Sw w``: where the measured and the estimated states go.
    Ts : float
    """

    F: np.ndarray
    G: np.ndarray
    H: np.ndarray
    Lr: np.ndarray
    poles: np.ndarray
    Sy: np.ndarray
    Sw: np.ndarray
    Ts: float = 0.0

    def estimate(self, z: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The full state estimate ``Sy y + Sw (z + Lr y)``."""
        y = np.asarray(y, float)
        return self.Sy @ y + self.Sw @ (np.asarray(z, float) + self.Lr @ y)

    def as_ss(self) -> ct.StateSpace:
        """The observer as a python-control system: inputs ``[x, phi, F]``, outputs the state estimate."""
        B = np.hstack([self.G, self.H])
        C = self.Sw
        D = np.hstack([self.Sy + self.Sw @ self.Lr, np.zeros((4, 1))])
        return ct.ss(self.F, B, C, D, self.Ts if self.Ts else 0, inputs=["x", "phi", "F"],
                     outputs=["x_hat", "xdot_hat", "phi_hat", "phidot_hat"], states=["z_xdot", "z_phidot"],
                     name="reduced_observer")


def _split(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, ...]:
    m, u = list(MEASURED), list(UNMEASURED)
    return A[np.ix_(m, m)], A[np.ix_(m, u)], A[np.ix_(u, m)], A[np.ix_(u, u)], B[m, :], B[u, :]


def _selectors() -> tuple[np.ndarray, np.ndarray]:
    Sy, Sw = np.zeros((4, 2)), np.zeros((4, 2))
    Sy[list(MEASURED), [0, 1]] = 1.0
    Sw[list(UNMEASURED), [0, 1]] = 1.0
    return Sy, Sw


def _build(A: np.ndarray, B: np.ndarray, target: np.ndarray, Ts: float) -> ReducedObserver:
    A11, A12, A21, A22, B1, B2 = _split(np.asarray(A, float), np.asarray(B, float))
    Lr = np.asarray(ct.place(A22.T, A12.T, list(target)), float).T
    F = A22 - Lr @ A12
    G = F @ Lr + A21 - Lr @ A11
    H = B2 - Lr @ B1
    Sy, Sw = _selectors()
    return ReducedObserver(F=F, G=G, H=H, Lr=Lr, poles=np.linalg.eigvals(F), Sy=Sy, Sw=Sw, Ts=Ts)


def _check_poles(poles: Sequence[complex], what: str) -> np.ndarray:
    p = np.asarray(poles, dtype=complex).ravel()
    if p.shape != (2,) or np.any(p.real >= 0) or not np.all(np.isfinite(p)):
        raise ValueError(f"{what}: the reduced-order observer needs 2 stable continuous poles, got {list(poles)!r}")
    if abs(p[0].imag) > 0 and not np.isclose(p[0], np.conj(p[1])):
        raise ValueError(f"{what}: complex poles come in conjugate pairs, got {list(poles)!r}")
    return p


def reduced_observer(params: RobotParams, poles: Sequence[complex]) -> ReducedObserver:
    """The continuous reduced-order observer with the two poles of ``F`` at ``poles``.

    Parameters
    ----------
    params : RobotParams
    poles : 2 complex
        Continuous observer poles (stable; a complex pair or two reals).

    Returns
    -------
    ReducedObserver
    """
    p = _check_poles(poles, "poles")
    A, B, _, _ = linear_model(params)
    return _build(A, B, p, 0.0)


def discrete_reduced_observer(params: RobotParams, poles: Sequence[complex], rate: float | None = None) -> ReducedObserver:
    """The discrete reduced-order observer at the loop rate, its poles at ``exp(poles Ts)``.

    Built from the ZOH plant ``Ad, Bd`` (:func:`host.design.discrete.discretise`).
    """
    p = _check_poles(poles, "poles")
    Ad, Bd, _, Ts = discretise(params, rate)
    return _build(Ad, Bd, np.exp(p * Ts), Ts)


class ReducedOrderController(DiscreteController):
    """:class:`DiscreteController` whose estimator is a reduced-order observer.

    Controller state ``[z (2), b_0 .. b_{d-1}]``; the ``M`` attribute holds ``Lr`` and
    :attr:`observer` the discrete :class:`ReducedObserver`.  The scenario and batch simulators
    (:func:`sim.plantsim.run_scenario_float`, :mod:`sim.batch`) read the full estimator's
    structure (``M`` (4, 2), the tilt estimate at ``z[2]``): give them :meth:`firmware_form`.
    """

    observer: ReducedObserver

    def initial_state(self, v: Sequence[float] | None = None) -> np.ndarray:
        """At rest: ``w_hat = 0``, i.e. ``z = -Lr y`` for the measurements ``v`` (0 without)."""
        z = np.zeros(self.n)
        if v is not None:
            z[:2] = -self.observer.Lr @ np.asarray(v[:2], float)
        return z

    def firmware_form(self) -> DiscreteController:
        """The same controller in the firmware's (full estimator's) structure, as it runs there.

        Filter gain ``M = Sy + Sw Lr`` (:func:`host.design.export.filter_gain`), state
        ``[p (4), b_0 .. b_{d-1}]`` with ``p`` the prediction of the delayed state: the measured
        states are the measurements, and ``p_w - Lr p_y`` is this controller's ``z``.  Same
        input-output behaviour (same closed-loop poles, plus two at zero), and what
        :mod:`host.design.robust`'s batch runs take (``design="reduced"``).
        """
        from host.design.discrete import assemble

        ob = self.observer
        return assemble(self.Ad, self.Bd, self.C, self.Ts, self.delay_steps, self.K, ob.Sy + ob.Sw @ ob.Lr,
                        self.kr, self.u_max, "reduced")

    def estimate(self, z: np.ndarray, v: Sequence[float]) -> np.ndarray:
        """Predicted current state ``xh = Ad^d xf + sum Ad^(d-1-i) Bd b_i``."""
        d = self.delay_steps
        xh = np.linalg.matrix_power(self.Ad, d) @ self.observer.estimate(z[:2], np.asarray(v[:2], float))
        for i in range(d):
            xh = xh + (np.linalg.matrix_power(self.Ad, d - 1 - i) @ self.Bd)[:, 0] * z[2 + i]
        return xh


def reduced_controller(
    params: RobotParams,
    K: Sequence[float],
    poles: Sequence[complex],
    rate: float | None = None,
    delay: float | None = None,
    *,
    u_max: float = np.inf,
) -> ReducedOrderController:
    """The discrete controller: reduced-order observer, predictor over the delay, ``u = -K xh + kr r``.

    Parameters
    ----------
    params : RobotParams
    K : 4 float
        Discrete state-feedback row (``u = -K x``), e.g. ``DiscreteController.K`` or ``dlqr``'s.
    poles : 2 complex
        Continuous observer poles (mapped to ``exp(s Ts)``).
    rate, delay : float, optional
        Loop rate (Hz) and measurement delay (s, whole ticks); default the robot file's.
    u_max : float
        Force saturation (N); none by default.

    Returns
    -------
    ReducedOrderController
        ``u = Cc z + Dc v``, ``z' = Ac z + Bc v + Bu u_sat`` with ``v = [x_meas, phi_meas, x_ref]``.
    """
    obs = discrete_reduced_observer(params, poles, rate)
    Ad, Bd, C, Ts = discretise(params, rate)
    d = delay_steps(params, 1.0 / Ts, delay)
    Kd = np.asarray(K, float).reshape(1, 4)
    if np.max(np.abs(np.linalg.eigvals(Ad - Bd @ Kd))) >= 1.0:
        raise ValueError("the state feedback does not stabilise the discrete plant")
    cx = np.array([[1.0, 0.0, 0.0, 0.0]])
    kr = float(1.0 / (cx @ np.linalg.solve(np.eye(4) - Ad + Bd @ Kd, Bd))[0, 0])
    Kf = Kd @ np.linalg.matrix_power(Ad, d)
    kb = np.array([(Kd @ np.linalg.matrix_power(Ad, d - 1 - i) @ Bd)[0, 0] for i in range(d)])
    # xf = Sw z + Py y with Py = Sy + Sw Lr
    Py = obs.Sy + obs.Sw @ obs.Lr
    n = 2 + d
    Ac, Bc, Bu = np.zeros((n, n)), np.zeros((n, 3)), np.zeros((n, 1))
    Cc, Dc = np.zeros((1, n)), np.zeros((1, 3))
    Ac[:2, :2] = obs.F
    Bc[:2, :2] = obs.G
    Cc[0, :2] = -(Kf @ obs.Sw)[0]
    Cc[0, 2:] = -kb
    Dc[0, :2] = -(Kf @ Py)[0]
    Dc[0, 2] = kr
    if d == 0:
        Bu[:2, 0] = obs.H[:, 0]
    else:
        Ac[:2, 2] = obs.H[:, 0]  # the observer steps with u[k-d] = b_0
        for i in range(d - 1):
            Ac[2 + i, 3 + i] = 1.0
        Bu[n - 1, 0] = 1.0
    ctrl = ReducedOrderController(
        Ac=Ac, Bc=Bc, Cc=Cc, Dc=Dc, Bu=Bu, Ts=Ts, delay_steps=d, u_max=float(u_max),
        Ad=Ad, Bd=Bd, C=C, K=Kd, M=obs.Lr, kr=kr, Kf=Kf, kb=kb, design="reduced",
    )
    ctrl.observer = obs
    return ctrl


def reduced_for(params: RobotParams, ctrl: DiscreteController,
                poles: Sequence[complex] | None = None) -> ReducedOrderController:
    """The reduced-order version of a full-estimator controller: the same state feedback
    ``ctrl.K``, loop rate, delay and force clamp, the observer poles ``poles`` (continuous,
    default :data:`REDUCED_POLES_DEFAULT`).

    Parameters
    ----------
    params : RobotParams
    ctrl : DiscreteController
        E.g. :func:`host.design.discrete.controller_ss` (the shipped design by default).
    poles : 2 complex, optional

    Returns
    -------
    ReducedOrderController
    """
    pl = REDUCED_POLES_DEFAULT if poles is None else poles
    return reduced_controller(params, ctrl.K[0], pl, 1.0 / ctrl.Ts, ctrl.delay_steps * ctrl.Ts, u_max=ctrl.u_max)


def back_emf_gain(params: RobotParams) -> float:
    """Force per cart speed (N s/m) of the drive's back-EMF: ``n g^2 kt^2 / (R r^2)``.

    The firmware (and :func:`sim.motor.duty_from_force`) compensates it with the *estimated*
    cart speed, so an error ``e`` of that estimate becomes a force error ``b e`` on the cart --
    44 N per m/s for the report's robot, against a force clamp of 2.9 N.
    """
    from sim.motor import motor_constants

    c = motor_constants(params)
    return float(c["n_motors"] * c["gear"] ** 2 * c["kt"] ** 2 / (c["R"] * c["r_wheel"] ** 2))


def noise_response(params: RobotParams, ctrl: DiscreteController, sigma_meas: Sequence[float], *,
                   back_emf: bool = True, sigma_force: float | None = None,
                   sigma_acc: Sequence[float] | None = None) -> dict[str, float]:
    """Steady-state standard deviations of the linear closed loop under white sensor noise.

    The delayed plant (``Ad, Bd``, ``delay_steps`` ticks on both outputs), the controller
    ``ctrl`` (any :class:`~host.design.discrete.DiscreteController`: the full estimator or a
    :class:`ReducedOrderController`), white measurement noise ``sigma_meas`` (x in m, phi in rad,
    per tick) and the Kalman design's process noise (:data:`host.design.discrete.SIGMA_FORCE`,
    ``SIGMA_ACC``).  With ``back_emf`` the force the cart gets is the command plus
    :func:`back_emf_gain` times the error of the controller's speed estimate (the firmware's
    compensation with the estimated speed); the controller stores the command.  No saturation:
    a force figure near the clamp means the loop spends its time saturated.

    Returns
    -------
    dict
        ``force`` (N, the force on the cart), ``command`` (N), ``speed_error`` (m/s, of the
        estimate the compensation uses), ``phi`` (rad), ``x`` (m).
    """
    import scipy.linalg as sl

    from host.design.discrete import SIGMA_ACC, SIGMA_FORCE

    sf = SIGMA_FORCE if sigma_force is None else float(sigma_force)
    sa = SIGMA_ACC if sigma_acc is None else tuple(sigma_acc)
    Ad, Bd, C, Ts, d = ctrl.Ad, ctrl.Bd, ctrl.C, ctrl.Ts, ctrl.delay_steps
    if d < 1:
        raise ValueError("noise_response needs a controller with a measurement delay of at least one tick")
    nc = ctrl.Ac.shape[0]
    N = 4 + 2 * d + nc  # plant, delay line q_i = C x[k-1-i], controller
    iz = slice(4 + 2 * d, N)
    A = np.zeros((N, N))
    W = np.zeros((N, 6))  # 4 process, 2 measurement noises
    Sy = np.zeros((2, N))
    Sy[:, 4 + 2 * (d - 1):4 + 2 * d] = np.eye(2)
    Dv = np.zeros((2, 6))
    Dv[:, 4:] = np.diag(np.asarray(sigma_meas, float))
    # command u_c = Cc zc + Dc y
    Kc = np.zeros((1, N))
    Kc[:, iz] = ctrl.Cc
    Kc += ctrl.Dc[:, :2] @ Sy
    Kcv = ctrl.Dc[:, :2] @ Dv
    # the controller's estimate xh = Ez zc + Ev y (x_ref 0)
    n = ctrl.n
    Ez = np.column_stack([ctrl.estimate(np.eye(n)[i], np.zeros(3)) for i in range(n)])
    Ev = np.column_stack([ctrl.estimate(np.zeros(n), np.eye(3)[i]) for i in range(3)])[:, :2]
    e_sp = np.zeros((1, N))
    e_sp[0, iz] = Ez[1]
    e_sp += Ev[1:2] @ Sy
    e_sp[0, 1] -= 1.0
    e_spv = Ev[1:2] @ Dv
    b = back_emf_gain(params) if back_emf else 0.0
    Ku, Kuv = Kc + b * e_sp, Kcv + b * e_spv
    A[:4, :4] = Ad
    A[:4] += Bd @ Ku
    W[:4] += Bd @ Kuv
    Qn = sf**2 * (Bd @ Bd.T) + np.diag([0.0, (sa[0] * Ts) ** 2, 0.0, (sa[1] * Ts) ** 2])
    W[:4, :4] = np.linalg.cholesky(Qn + 1e-18 * np.eye(4))
    A[4:6, :4] = C
    for i in range(1, d):
        A[4 + 2 * i:6 + 2 * i, 4 + 2 * (i - 1):4 + 2 * i] = np.eye(2)
    A[iz, iz] = ctrl.Ac
    A[iz] += ctrl.Bc[:, :2] @ Sy + ctrl.Bu @ Kc
    W[iz] += ctrl.Bc[:, :2] @ Dv + ctrl.Bu @ Kcv
    if np.max(np.abs(np.linalg.eigvals(A))) >= 1.0:
        raise ValueError("the closed loop is unstable")
    X = sl.solve_discrete_lyapunov(A, W @ W.T)

    def sd(row: np.ndarray, rowv: np.ndarray) -> float:
        return float(np.sqrt((row @ X @ row.T + rowv @ rowv.T)[0, 0]))

    return {"force": sd(Ku, Kuv), "command": sd(Kc, Kcv), "speed_error": sd(e_sp, e_spv),
            "phi": float(np.sqrt(X[2, 2])), "x": float(np.sqrt(X[0, 0]))}
