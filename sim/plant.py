"""The pendulum-on-cart plant: nonlinear equations of motion and their linearisation.

State ``[x, xdot, phi, phidot]``: cart position (m), cart velocity (m/s), pendulum
deviation from upright (rad, positive in the report's convention theta = pi + phi) and
its rate.  Input: horizontal force on the cart ``F`` (N).

Equations of motion, the report's (2.3) and (2.6) with theta = pi + phi and nothing
dropped (full sin/cos and the centripetal term)::

    (M + m) xdd + b xd - m L cos(phi) phidd + m L phid^2 sin(phi) = F
    (I + m L^2) phidd - m g L sin(phi) = m L cos(phi) xdd

This module is the one place they are written: :func:`accelerations` solves them for
``(xdd, phidd)`` on scalars or arrays, and every simulator takes them from here -- the
scenario simulator (:class:`sim.plantsim.PlantSim`), the numpy batch reference
(:func:`sim.batch._loop_numpy`, through :func:`dynamics`), the catch study
(:mod:`host.design.catch`: the first equation split at the force, :func:`xddot_affine` and
:func:`force_for_xddot`, the second solved for the tilt, :func:`phiddot_given_xddot`); the
compiled batch kernel (:mod:`sim.batch_kernel`) is a specialised copy for speed, held
bit-identical to the numpy reference by ``tests/test_batch_kernel.py`` and to
:func:`accelerations` by ``tests/test_plant_equations.py``.  The expression trees here are
the ones those copies evaluate (IEEE arithmetic is not associative): change them together.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping

import control as ct
import numpy as np

from .params import RobotParams

__all__ = [
    "STATES",
    "accelerations",
    "pivot_fixed_phiddot",
    "xddot_affine",
    "force_for_xddot",
    "phiddot_given_xddot",
    "dynamics",
    "make_nlsys",
    "linear_model",
    "reduced_model",
    "rk4_step",
    "simulate",
    "impulse_jump",
]

STATES = ("x", "xdot", "phi", "phidot")


def _phys(params: RobotParams | Mapping[str, float]) -> tuple[float, ...]:
    p = params.physical if isinstance(params, RobotParams) else params
    return p["M"], p["m"], p["L"], p["I"], p["b"], p["g"]


def accelerations(F: Any, xd: Any, phid: Any, s: Any, c: Any, Mt: Any, mL: Any, J: Any, b: Any,
                  mLg: Any) -> tuple[Any, Any]:
    """The equations of motion solved for the accelerations (scalars or arrays alike).

    Parameters
    ----------
    F : float or ndarray
        Force on the cart (N), friction other than ``b`` already in it.
    xd, phid : float or ndarray
        Cart speed (m/s) and tilt rate (rad/s).
    s, c : float or ndarray
        ``sin(phi)``, ``cos(phi)``.
    Mt, mL, J, b, mLg : float or ndarray
        ``M + m``, ``m L``, ``I + m L^2``, the cart friction ``b`` and ``m L g``.

    Returns
    -------
    (xddot, phiddot)
    """
    rhs1 = F - b * xd - mL * phid * phid * s
    rhs2 = mLg * s
    mc = mL * c
    det = Mt * J - mc * mc
    return (J * rhs1 + mc * rhs2) / det, (mc * rhs1 + Mt * rhs2) / det


def pivot_fixed_phiddot(s: Any, mLg: Any, J: Any) -> Any:
    """``phiddot`` of the pendulum while the cart stands still (stuck by static friction)."""
    return mLg * s / J


def xddot_affine(xd: Any, phid: Any, s: Any, c: Any, Mt: Any, mL: Any, J: Any, b: Any, g: Any) -> tuple[Any, Any]:
    """The cart acceleration as an affine function of the force: ``xddot = a0 + gain F``.

    :func:`accelerations`' first row split at ``F`` (the catch study's drive limits).
    Returns ``(a0, gain)``.
    """
    det = Mt * J - (mL * c) ** 2
    return (J * (-b * xd - mL * phid * phid * s) + mL * c * mL * g * s) / det, J / det


def force_for_xddot(xdd: Any, xd: Any, phid: Any, s: Any, c: Any, Mt: Any, mL: Any, J: Any, b: Any, g: Any) -> Any:
    """The force on the cart that gives the cart acceleration ``xdd`` (:func:`xddot_affine` inverted)."""
    det = Mt * J - (mL * c) ** 2
    return (xdd * det - mL * c * mL * g * s) / J + b * xd + mL * phid * phid * s


def phiddot_given_xddot(xdd: Any, s: Any, c: Any, mL: Any, J: Any, g: Any) -> Any:
    """The second equation solved for the tilt: ``J phidd = m g L sin + m L cos xdd`` (the cart's
    acceleration as the input)."""
    return (mL * g * s + mL * c * xdd) / J


def dynamics(t: float, x: np.ndarray, u: np.ndarray, params: RobotParams | Mapping[str, float]) -> np.ndarray:
    """Right-hand side of the nonlinear plant, ``updfcn(t, x, u, params)``.

    Parameters
    ----------
    t : float
        Time (unused: the plant is time invariant).
    x : array_like, shape (4,) or (4, N)
        State ``[x, xdot, phi, phidot]``; a second axis evaluates a batch.
    u : array_like, shape (1,) or (N,)
        Force on the cart (N).
    params : RobotParams or mapping
        Physical parameters (``M, m, L, I, b, g``).

    Returns
    -------
    ndarray
        ``[xdot, xddot, phidot, phiddot]`` with the shape of ``x``.
    """
    M, m, L, I, b, g = _phys(params)
    _, xd, phi, phid = x[0], x[1], x[2], x[3]
    F = np.reshape(u, -1)[0] if np.ndim(x) == 1 else np.asarray(u)
    mL = m * L
    xdd, phidd = accelerations(F, xd, phid, np.sin(phi), np.cos(phi), M + m, mL, I + m * L * L, b, mL * g)
    return np.array([xd, xdd, phid, phidd])


def impulse_jump(phi: float, impulse: float, Mt: float, mL: float, J: float) -> tuple[float, float]:
    """Velocity jump ``(dxdot, dphidot)`` of a Dirac ``impulse`` (N s) on the cart at tilt ``phi``.

    The generalised momenta jump by ``[impulse, 0]``: ``Mq [dxd, dphid] = [impulse, 0]`` with the
    mass matrix ``Mq = [[M + m, -mL cos], [-mL cos, J]]`` (``Mt = M + m``, ``mL = m L``,
    ``J = I + m L^2``, as in :func:`dynamics`).  The scenario simulator applies it at each kick
    (:class:`sim.plantsim.PlantSim`); the robust evaluation starts its kick runs from it.
    """
    c = math.cos(phi)
    det = Mt * J - (mL * c) ** 2
    return J * impulse / det, mL * c * impulse / det


def make_nlsys(params: RobotParams, name: str = "pendulum") -> ct.NonlinearIOSystem:
    """The plant as a python-control ``nlsys`` with outputs ``x`` and ``phi``.

    Parameters
    ----------
    params : RobotParams
        Robot parameters.
    name : str
        System name.

    Returns
    -------
    control.NonlinearIOSystem
        Inputs ``F``; states ``x, xdot, phi, phidot``; outputs ``x, phi``.
    """
    return ct.nlsys(
        dynamics,
        lambda t, x, u, p: np.array([x[0], x[2]]),
        inputs=["F"],
        outputs=["x", "phi"],
        states=list(STATES),
        params=params.physical,
        name=name,
    )


def linear_model(params: RobotParams | Mapping[str, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Analytic linearisation about upright, the report's eqs. (2.13)-(2.15).

    Returns
    -------
    A : ndarray, shape (4, 4)
    B : ndarray, shape (4, 1)
    C : ndarray, shape (2, 4)
        Measures ``x`` and ``phi``.
    D : ndarray, shape (2, 1)
    """
    M, m, L, I, b, g = _phys(params)
    q = I * (M + m) + M * m * L**2
    A = np.array(
        [
            [0.0, 1.0, 0.0, 0.0],
            [0.0, -(I + m * L**2) * b / q, m**2 * g * L**2 / q, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            [0.0, -m * L * b / q, m * g * L * (M + m) / q, 0.0],
        ]
    )
    B = np.array([[0.0], [(I + m * L**2) / q], [0.0], [m * L / q]])
    C = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    D = np.zeros((2, 1))
    return A, B, C, D


def reduced_model(params: RobotParams | Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """The 3-state model ``[xdot, phi, phidot]`` of eqs. (2.16)-(2.17) (x dropped).

    Returns
    -------
    A : ndarray, shape (3, 3)
    B : ndarray, shape (3, 1)
    """
    A, B, _, _ = linear_model(params)
    return A[1:, 1:].copy(), B[1:].copy()


def rk4_step(f: Callable[[np.ndarray, float], np.ndarray], x: np.ndarray, u: float, h: float) -> np.ndarray:
    """One classical Runge-Kutta step of ``xdot = f(x, u)`` with ``u`` held."""
    k1 = f(x, u)
    k2 = f(x + 0.5 * h * k1, u)
    k3 = f(x + 0.5 * h * k2, u)
    k4 = f(x + h * k3, u)
    return x + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)


def simulate(
    params: RobotParams,
    x0: np.ndarray,
    duration: float,
    *,
    force: Callable[[float], float] | None = None,
    controller: Callable[[float, np.ndarray], float] | None = None,
    dt: float = 1e-3,
    substeps: int = 4,
    u_limit: float | None = None,
) -> dict[str, np.ndarray]:
    """Integrate the nonlinear plant with RK4, optionally closed around a controller.

    The controller (if any) is sampled every ``dt`` and its output held (zero-order
    hold) over ``substeps`` RK4 steps; an external disturbance ``force(t)`` adds to it.

    Parameters
    ----------
    params : RobotParams
        Robot parameters.
    x0 : array_like, shape (4,)
        Initial state.
    duration : float
        Simulated time (s).
    force : callable, optional
        Disturbance force ``force(t)`` in N added at the cart.
    controller : callable, optional
        ``controller(t, x) -> F``; called at each sample with the true state.
    dt : float
        Sample period (s) of the log and the controller.
    substeps : int
        RK4 steps per sample.
    u_limit : float, optional
        Saturation of the controller force (N).

    Returns
    -------
    dict
        Arrays ``t, x, xdot, phi, phidot, force`` (force: the total applied force).
    """
    if dt <= 0 or substeps < 1 or duration < 0:
        raise ValueError("dt and substeps must be positive and duration non-negative")
    phys = params.physical
    n = int(round(duration / dt)) + 1
    t = np.arange(n) * dt
    X = np.empty((n, 4))
    U = np.zeros(n)
    x = np.asarray(x0, dtype=float).copy()
    h = dt / substeps

    def f(xx: np.ndarray, uu: float) -> np.ndarray:
        return dynamics(0.0, xx, np.array([uu]), phys)

    for k in range(n):
        X[k] = x
        u = 0.0
        if controller is not None:
            u = float(controller(t[k], x))
            if u_limit is not None:
                u = min(max(u, -u_limit), u_limit)
        if force is not None:
            u += float(force(t[k]))
        U[k] = u
        if k < n - 1:
            for _ in range(substeps):
                x = rk4_step(f, x, u, h)
    return {"t": t, "x": X[:, 0], "xdot": X[:, 1], "phi": X[:, 2], "phidot": X[:, 3], "force": U}
