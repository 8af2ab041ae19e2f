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
           "discrete_reduced_observer", "ReducedOrderController", "reduced_controller", "reduced_for"]

REDUCED_POLES_DEFAULT = (-4.0, -5.0)
"""Continuous observer poles (rad/s) of the exported reduced-order table (``upright export
--estimator reduced``).  Chosen in HIL (firmware on the unix port, lockstep) on the report's
scenarios with the shipped state feedback and force clamp: faster poles pass more of the
sensors' noise and counts into the speed estimates -- the report's uniform 5 mm / 5 mrad noise
then breaks the 5 m/s^2 acceleration limit (peak 3.5 m/s^2 at -4/-5, 4.2 at -5/-6, 4.8 at -6/-7,
5.5 at -7/-8) -- and at -5/-6 the kick's tilt settles in a one-count limit cycle past the band
(3.12 s); -4/-5 meets every constraint the full estimator meets there except under the report's
white noise.  No poles keep the pendulum up under that noise (0.07 rad rms on the angle per tick,
fed straight into the force): it needs the full estimator's filtering."""

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
