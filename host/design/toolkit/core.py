"""The continuous-time steps of the toolkit: the plant, state feedback, estimators, controllers as
python-control systems, margins (re-exported by :mod:`host.design.toolkit`)."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any, Sequence

import control as ct
import numpy as np

from host.design import analysis
from host.design import controllers as _ctl
from host.design.reduced import ReducedObserver, reduced_observer
from sim.params import RobotParams
from sim.plant import STATES, linear_model, make_nlsys

__all__ = [
    "CONVENTIONS", "StateFeedback", "Observer", "plant", "plant_nonlinear", "transfer_functions", "poles_from_spec",
    "lqr", "place", "precompensator", "observer", "kalman", "reduced", "pid", "state_feedback_loop",
    "observer_controller", "reduced_controller_ss", "margins", "complex_list",
]

CONVENTIONS: dict[str, str] = {
    "state": "[x, xdot, phi, phidot]: cart position (m), cart velocity (m/s), tilt from upright (rad), tilt rate (rad/s)",
    "angle": "theta = pi + phi: theta is the report's angle from the downward vertical, phi = 0 upright; phi > 0 "
             "leans the pendulum towards -x (a force F > 0 on the cart makes phi grow)",
    "input": "F (N): horizontal force on the cart, positive towards +x (no drive model: the motor section is not used)",
    "outputs": "y = [x, phi] (C selects them; D = 0)",
    "state_feedback": "u = -K x + Nbar r, r the cart-position reference (m); Nbar gives unit DC gain from r to x",
    "observer": "xhat' = A xhat + B u + L (y - C xhat) (continuous; discrete: xhat[k+1] = Ad xhat[k] + Bd u[k] + "
                "Ld (y[k] - C xhat[k]), the predictor form)",
    "reduced_observer": "z' = F z + G y + H u, [xdot, phidot]_hat = z + Lr y; x and phi from the sensors",
    "kalman": "process noise: a white force on the cart (sigma_force, N); measurement noise sigma_x (m), sigma_phi "
              "(rad); continuous: control.lqe(A, B, C, sigma_force^2, diag(sigma^2)); discrete: control.dlqe with "
              "the same numbers as per-sample variances",
    "inertia": "the equations use I_cm (about the centre of mass); I_pivot = I_cm + m L_cm^2",
    "discrete": "zero-order hold at Ts = 1/rate (control.c2d(..., 'zoh')); dlqr weights Q Ts, R Ts; poles placed at "
                "exp(s Ts) of the continuous ones; a delay of d ticks: y[k] = C x[k-d]",
    "margins": "control.stability_margins of the loop broken at the plant input, negative feedback: gain margin "
               "(factor; < 1 means the loop tolerates a gain reduction down to it), phase margin (deg), crossover "
               "frequencies (rad/s); null where there is no crossover (an infinite margin)",
    "transfer_functions": "num/den coefficients, highest power of s first",
    "pid": "u = -C(s) phi with C(s) = Kp + Ki/s + Kd s/(1 + s/N): the loop L = P_phi C, negative feedback",
    "complex": "complex numbers as [re, im]",
}


def complex_list(values: Sequence[complex] | np.ndarray) -> list[list[float]]:
    """Complex numbers as ``[[re, im], ...]`` sorted by real part then imaginary (JSON)."""
    vals = sorted((complex(v) for v in np.ravel(values)), key=lambda z: (round(z.real, 9), z.imag))
    return [[z.real, z.imag] for z in vals]


def _mat(a: Any) -> list:
    return np.asarray(a, float).tolist()


# ---------------------------------------------------------------- the plant
def plant(params: RobotParams) -> ct.StateSpace:
    """The linearised plant about upright as ``control.StateSpace`` (input F, outputs x, phi)."""
    A, B, C, D = linear_model(params)
    return ct.ss(A, B, C, D, inputs=["F"], outputs=["x", "phi"], states=list(STATES), name="cartpole")


def plant_nonlinear(params: RobotParams) -> ct.NonlinearIOSystem:
    """The nonlinear plant as ``control.nlsys`` (``updfcn(t, x, u, params)``; :func:`sim.plant.dynamics`).

    ``control.linearize(plant_nonlinear(p), [0, 0, 0, 0], [0])`` gives :func:`plant`.
    """
    return make_nlsys(params, name="cartpole")


def transfer_functions(params: RobotParams) -> dict[str, ct.TransferFunction]:
    """``{"x": X/F, "phi": Phi/F}``, numerically cleaned (:func:`host.design.analysis.clean_tf`)."""
    return analysis.transfer_functions(params)


def poles_from_spec(overshoot: float, settling: float, extra: Sequence[float] = (2.1, 2.14)) -> np.ndarray:
    """Four closed-loop poles from a step spec: the dominant pair for ``overshoot`` (fraction) and
    ``settling`` (2 %, s; ``Ts = 4 / (zeta omega)``) plus two real poles ``extra`` times deeper (report §3.2)."""
    zeta, omega = _ctl.zeta_omega_from_spec(overshoot, settling)
    return _ctl.dominant_poles(zeta, omega, extra)


# ---------------------------------------------------------------- state feedback
@dataclass(frozen=True)
class StateFeedback:
    """A state-feedback design ``u = -K x + Nbar r``.

    Attributes
    ----------
    K : ndarray (4,)
    Nbar : float
    poles : ndarray
        Closed-loop poles, eigenvalues of ``A - B K`` (``Ad - Bd K`` if discrete).
    Ts : float
        0 for continuous.
    """

    K: np.ndarray
    Nbar: float
    poles: np.ndarray
    Ts: float = 0.0

    def as_ss(self) -> ct.StateSpace:
        """The static controller: inputs ``[x, xdot, phi, phidot, r]``, output ``F``."""
        D = np.hstack([-self.K, [self.Nbar]])[None, :]
        return ct.ss([], [], [], D, self.Ts if self.Ts else 0, inputs=[*STATES, "r"], outputs=["F"],
                     name="state_feedback")

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {"K": _mat(self.K), "Nbar": self.Nbar, "poles": complex_list(self.poles)}


def precompensator(A: np.ndarray, B: np.ndarray, K: np.ndarray, Ts: float = 0.0) -> float:
    """``Nbar`` for unit DC gain from ``r`` to ``x``: ``-1 / (C_x (A - B K)^-1 B)``, or
    ``1 / (C_x (I - Ad + Bd K)^-1 Bd)`` in discrete time."""
    cx = np.array([[1.0, 0.0, 0.0, 0.0]])
    Acl = np.asarray(A) - np.asarray(B) @ np.atleast_2d(K)
    if Ts:
        return float(1.0 / (cx @ np.linalg.solve(np.eye(4) - Acl, B))[0, 0])
    return float(-1.0 / (cx @ np.linalg.solve(Acl, B))[0, 0])


def _weights(Q: Sequence[float] | np.ndarray, R: float) -> tuple[np.ndarray, np.ndarray]:
    q = np.asarray(Q, float)
    q = np.diag(q) if q.shape == (4,) else q
    if q.shape != (4, 4) or not np.all(np.isfinite(q)) or np.any(np.linalg.eigvalsh(0.5 * (q + q.T)) < -1e-12):
        raise ValueError(f"Q must be 4 non-negative weights (the diagonal) or a 4x4 positive semidefinite matrix, got {Q!r}")
    r = float(R)
    if not (math.isfinite(r) and r > 0):
        raise ValueError(f"R must be > 0, got {R!r}")
    return q, np.array([[r]])


def lqr(params: RobotParams, Q: Sequence[float] | np.ndarray, R: float) -> StateFeedback:
    """Continuous LQR (``control.lqr``) for ``Q`` (4 weights or 4x4) and ``R``."""
    A, B, _, _ = linear_model(params)
    q, r = _weights(Q, R)
    K, _, E = ct.lqr(A, B, q, r)
    K = np.asarray(K, float).ravel()
    return StateFeedback(K=K, Nbar=precompensator(A, B, K), poles=np.asarray(E))


def _poles(poles: Sequence[complex], n: int, what: str) -> np.ndarray:
    p = np.asarray(poles, dtype=complex).ravel()
    if p.shape != (n,) or not np.all(np.isfinite(p)):
        raise ValueError(f"{what}: expected {n} poles, got {list(poles)!r}")
    if np.any(p.real >= 0):
        raise ValueError(f"{what}: every pole must have a negative real part, got {list(poles)!r}")
    if not np.allclose(np.sort_complex(p), np.sort_complex(np.conj(p))):
        raise ValueError(f"{what}: complex poles must come in conjugate pairs, got {list(poles)!r}")
    return p.real.copy() if np.all(p.imag == 0) else p


def place(params: RobotParams, poles: Sequence[complex]) -> StateFeedback:
    """Pole placement (``control.place``) of ``A - B K`` at 4 ``poles``."""
    A, B, _, _ = linear_model(params)
    p = _poles(poles, 4, "poles")
    K = np.asarray(ct.place(A, B, p), float).ravel()
    return StateFeedback(K=K, Nbar=precompensator(A, B, K), poles=np.linalg.eigvals(A - B @ K[None, :]))


# ---------------------------------------------------------------- estimators
@dataclass(frozen=True)
class Observer:
    """A full-order observer gain ``L`` (4, 2) and its poles (eigenvalues of ``A - L C``)."""

    L: np.ndarray
    poles: np.ndarray
    Ts: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {"L": _mat(self.L), "poles": complex_list(self.poles)}


def observer(params: RobotParams, poles: Sequence[complex]) -> Observer:
    """Luenberger observer for ``y = [x, phi]``: ``control.place(A.T, C.T, poles).T``."""
    A, _, C, _ = linear_model(params)
    p = _poles(poles, 4, "observer poles")
    L = np.asarray(ct.place(A.T, C.T, p), float).T
    return Observer(L=L, poles=np.linalg.eigvals(A - L @ C))


def _noise(sigma_force: float, sigma_meas: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    s = [float(sigma_force), *(float(v) for v in sigma_meas)]
    if len(s) != 3 or not all(math.isfinite(v) and v > 0 for v in s):
        raise ValueError(f"Kalman noises must be 3 numbers > 0 (sigma_force, sigma_x, sigma_phi), got {s!r}")
    return np.array([[s[0] ** 2]]), np.diag([s[1] ** 2, s[2] ** 2])


def kalman(params: RobotParams, sigma_force: float, sigma_meas: Sequence[float]) -> Observer:
    """Steady-state Kalman-Bucy gain (``control.lqe(A, B, C, QN, RN)``): a white force on the cart."""
    A, B, C, _ = linear_model(params)
    QN, RN = _noise(sigma_force, sigma_meas)
    L, _, E = ct.lqe(A, B, C, QN, RN)
    return Observer(L=np.asarray(L, float), poles=np.asarray(E))


def reduced(params: RobotParams, poles: Sequence[complex]) -> ReducedObserver:
    """The continuous reduced-order observer of ``[xdot, phidot]`` (:mod:`host.design.reduced`)."""
    return reduced_observer(params, poles)


# ---------------------------------------------------------------- controllers as systems
def pid(kp: float, ki: float, kd: float, n: float = _ctl.DERIVATIVE_FILTER) -> ct.TransferFunction:
    """PID on the angle, ``Kp + Ki/s + Kd s / (1 + s/n)``, acting as ``u = -C(s) phi``: the loop
    ``L = P_phi C`` closed with negative feedback, as in the report (the cart drifts: x is not fed back)."""
    return _ctl.pid_tf((kp, ki, kd), n)


def state_feedback_loop(params: RobotParams, K: Sequence[float]) -> ct.TransferFunction:
    """The loop broken at the plant input, ``K (sI - A)^-1 B``."""
    A, B, _, _ = linear_model(params)
    return ct.tf(ct.ss(A, B, np.atleast_2d(np.asarray(K, float)), 0))


def observer_controller(params: RobotParams, K: Sequence[float], L: np.ndarray, Nbar: float = 0.0) -> ct.StateSpace:
    """The observer-based controller: inputs ``[x, phi, r]``, output ``F``.

    ``xhat' = (A - B K - L C) xhat + L y + B Nbar r``, ``F = -K xhat + Nbar r``.
    """
    A, B, C, _ = linear_model(params)
    K = np.atleast_2d(np.asarray(K, float))
    L = np.asarray(L, float)
    Ac = A - B @ K - L @ C
    Bc = np.hstack([L, B * Nbar])
    return ct.ss(Ac, Bc, -K, np.array([[0.0, 0.0, Nbar]]), inputs=["x", "phi", "r"], outputs=["F"],
                 states=[f"{s}_hat" for s in STATES], name="observer_controller")


def reduced_controller_ss(params: RobotParams, K: Sequence[float], obs: ReducedObserver, Nbar: float = 0.0) -> ct.StateSpace:
    """The controller with the reduced-order observer: inputs ``[x, phi, r]``, output ``F``.

    ``u = -K (Sy y + Sw (z + Lr y)) + Nbar r`` substituted into ``z' = F z + G y + H u``.
    """
    K = np.atleast_2d(np.asarray(K, float))
    Py = obs.Sy + obs.Sw @ obs.Lr
    Ac = obs.F - obs.H @ K @ obs.Sw
    Bc = np.hstack([obs.G - obs.H @ K @ Py, obs.H * Nbar])
    Cc = -K @ obs.Sw
    Dc = np.hstack([-K @ Py, [[Nbar]]])
    return ct.ss(Ac, Bc, Cc, Dc, obs.Ts if obs.Ts else 0, inputs=["x", "phi", "r"], outputs=["F"],
                 states=["z_xdot", "z_phidot"], name="reduced_controller")


def margins(loop: ct.LTI) -> dict[str, float | None]:
    """``control.stability_margins`` of a SISO loop (negative feedback): gm, pm (deg), wg, wp (rad/s)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # python-control compares nan responses internally
        gm, pm, _, wg, wp, _ = ct.stability_margins(loop)

    def num(v: float) -> float | None:
        return float(v) if math.isfinite(v) else None  # null: no crossover (an infinite margin)

    return {"gain_margin": num(gm), "phase_margin_deg": num(pm), "w_gain_crossover": num(wp),
            "w_phase_crossover": num(wg)}


def _input_loop(params: RobotParams, ctrl_y: ct.StateSpace) -> ct.LTI:
    # u = ctrl_y [x, phi] (r = 0); loop broken at u, negative-feedback convention: L = -ctrl_y P
    P = plant(params)
    return -ct.series(P, ctrl_y[:, :2])
