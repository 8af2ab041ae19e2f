"""DC motor and H-bridge drive model: PWM duty -> cart force.

The cart is driven by ``n_motors`` identical brushed DC motors in parallel, each through a
gearbox of reduction ``gear`` (motor turns per wheel turn) onto a wheel of radius
``r_wheel``.  The H-bridge applies ``V = duty / DUTY_MAX * V_supply`` (the supply-voltage
limit is the duty range itself); the armature inductance is neglected (electrical time
constant << control period), so the current follows the voltage instantly::

    w  = gear * xdot / r_wheel            motor shaft speed (rad/s)
    i  = (V - kt * w) / R                 armature current (A), back-EMF kt*w
    F  = n_motors * gear * kt * i / r_wheel   force on the cart (N)

``kt`` is both the torque constant (N m/A) and the back-EMF constant (V s/rad).

Plant realism (``docs/parameters.md``, "Plant realism"): the bridge's deadband ``deadband``
and minimum duty ``duty_min`` (fractions of full duty) act on the applied voltage
(:func:`bridge_fraction`)::

    u = duty / DUTY_MAX ;  a = |u| if |u| >= duty_min else 0 ;  V = sign(u) max(a - deadband, 0) V_supply

Both default to 0 (the ideal bridge: ``V = duty / DUTY_MAX * V_supply``).  The gear backlash
(``backlash``) needs a state and lives in the simulators (:mod:`sim.plantsim`, :mod:`sim.batch`).  Every
function is numpy-broadcast: ``duty`` and ``xdot`` may be scalars or arrays of any
(broadcast-compatible) shape, and ``params`` may be a :class:`~sim.params.RobotParams` or a
mapping whose motor entries are scalars *or arrays* (one value per batch member), which is
how the batch simulator varies motor constants.

The firmware implements :func:`duty_from_force` (the inverse, with back-EMF compensation
from its estimate of the cart speed) in fixed point; the plant side uses
:func:`force_from_duty`.
"""

from __future__ import annotations

from typing import Mapping, Union

import numpy as np

from .params import RobotParams

__all__ = [
    "DUTY_MAX",
    "MOTOR_KEYS",
    "motor_constants",
    "force_from_duty",
    "duty_from_force",
    "force_limits",
    "stall_force",
    "no_load_speed",
    "back_emf_damping",
    "current_from_duty",
    "bridge_fraction",
    "BRIDGE_KEYS",
]

DUTY_MAX = 32767
"""Full-scale PWM duty: ``duty`` is an int in ``[-DUTY_MAX, DUTY_MAX]`` (fraction of V_supply)."""

MOTOR_KEYS = ("V_supply", "R", "kt", "gear", "r_wheel", "n_motors")

BRIDGE_KEYS = ("deadband", "duty_min")
"""The H-bridge's realism parameters (fractions of full duty; absent from a mapping = 0)."""

ParamsLike = Union[RobotParams, Mapping[str, "float | np.ndarray"]]


def motor_constants(params: ParamsLike) -> dict[str, np.ndarray | float]:
    """The motor entries of ``params`` (scalars or arrays), keyed by bare name.

    Parameters
    ----------
    params : RobotParams or mapping
        Robot parameters, or a mapping with at least :data:`MOTOR_KEYS`.

    Returns
    -------
    dict
        ``V_supply, R, kt, gear, r_wheel, n_motors``.

    Raises
    ------
    KeyError
        If a mapping lacks one of the motor keys.
    """
    if isinstance(params, RobotParams):
        vals = params.values  # direct dotted lookup: RobotParams.__getattr__ scans every key
        return {k: vals[f"motor.{k}"] for k in MOTOR_KEYS}
    missing = [k for k in MOTOR_KEYS if k not in params]
    if missing:
        raise KeyError(f"motor parameters missing: {', '.join(missing)}")
    return {k: params[k] for k in MOTOR_KEYS}


def _force_per_amp(c: Mapping[str, np.ndarray | float]) -> np.ndarray | float:
    # N of cart force per A of armature current (all motors together)
    return c["n_motors"] * c["gear"] * c["kt"] / c["r_wheel"]


def _bridge(params: ParamsLike) -> tuple[np.ndarray | float, np.ndarray | float]:
    if isinstance(params, RobotParams):
        return params.values["motor.deadband"], params.values["motor.duty_min"]
    return params.get("deadband", 0.0), params.get("duty_min", 0.0)


def bridge_fraction(duty: np.ndarray | int, params: ParamsLike) -> np.ndarray:
    """The fraction of the supply the H-bridge applies at ``duty`` (in ``[-1, 1]``).

    ``u = clip(duty, +-DUTY_MAX) / DUTY_MAX``; with a minimum duty a pulse narrower than
    ``duty_min`` applies nothing, and the deadband takes ``deadband`` off every pulse:
    ``sign(u) * max(a - deadband, 0)`` with ``a = |u|`` if ``|u| >= duty_min`` else 0.  Without
    them (the defaults) exactly ``u``.

    Parameters
    ----------
    duty : int or array_like
        PWM duty in ``[-32767, 32767]`` (clipped to that range).
    params : RobotParams or mapping
        ``deadband`` and ``duty_min`` (scalars or per-batch arrays; absent = 0).
    """
    u = np.clip(np.asarray(duty, dtype=float), -DUTY_MAX, DUTY_MAX) / DUTY_MAX
    db, dmin = _bridge(params)
    if np.any(np.asarray(db) != 0) or np.any(np.asarray(dmin) != 0):
        a = np.abs(u)
        a = np.where(a < dmin, 0.0, a)
        a = a - db
        a = np.where(a > 0.0, a, 0.0)
        u = np.copysign(a, u)
    return u


def current_from_duty(duty: np.ndarray | int, xdot: np.ndarray | float, params: ParamsLike) -> np.ndarray:
    """Armature current of each motor (A) for a duty and a cart speed.

    Parameters
    ----------
    duty : int or array_like
        PWM duty in ``[-DUTY_MAX, DUTY_MAX]``; values outside are clipped (the bridge
        cannot apply more than the supply); the bridge's deadband and minimum duty
        (:func:`bridge_fraction`) apply.
    xdot : float or array_like
        Cart speed (m/s).
    params : RobotParams or mapping
        Motor parameters (scalars or arrays).

    Returns
    -------
    ndarray
        Current per motor (A), broadcast shape of the inputs.
    """
    c = motor_constants(params)
    V = bridge_fraction(duty, params) * c["V_supply"]
    w = c["gear"] * np.asarray(xdot, dtype=float) / c["r_wheel"]
    return (V - c["kt"] * w) / c["R"]


def force_from_duty(duty: np.ndarray | int, xdot: np.ndarray | float, params: ParamsLike) -> np.ndarray:
    """Cart force (N) produced by the drive at a duty and cart speed.

    ``V = duty/32767 * V_supply``, ``i = (V - kt*w)/R`` with ``w = gear*xdot/r_wheel``,
    ``F = n_motors*gear*kt*i/r_wheel``.

    Parameters
    ----------
    duty : int or array_like
        PWM duty in ``[-32767, 32767]`` (clipped to that range).
    xdot : float or array_like
        Cart speed (m/s).
    params : RobotParams or mapping
        Motor parameters (scalars or per-batch arrays).

    Returns
    -------
    ndarray
        Force on the cart (N), broadcast shape of the inputs (0-d for scalars).
    """
    c = motor_constants(params)
    return _force_per_amp(c) * current_from_duty(duty, xdot, params)


def duty_from_force(force: np.ndarray | float, xdot: np.ndarray | float, params: ParamsLike) -> np.ndarray:
    """Inverse drive model: the duty that produces ``force`` at cart speed ``xdot``.

    The back-EMF at ``xdot`` (the controller's *estimate* of the cart speed) is compensated;
    the result is rounded to the nearest integer and clipped to ``[-32767, 32767]`` (the
    supply-voltage limit).  This is the float reference of the firmware's fixed-point mapping.

    Parameters
    ----------
    force : float or array_like
        Requested cart force (N).
    xdot : float or array_like
        Estimated cart speed (m/s).
    params : RobotParams or mapping
        Motor parameters.

    Returns
    -------
    ndarray of int64
        Duty, broadcast shape of the inputs.
    """
    c = motor_constants(params)
    i = np.asarray(force, dtype=float) / _force_per_amp(c)
    w = c["gear"] * np.asarray(xdot, dtype=float) / c["r_wheel"]
    V = i * c["R"] + c["kt"] * w
    d = np.rint(V / c["V_supply"] * DUTY_MAX)
    return np.clip(d, -DUTY_MAX, DUTY_MAX).astype(np.int64)


def force_limits(xdot: np.ndarray | float, params: ParamsLike) -> tuple[np.ndarray, np.ndarray]:
    """The most negative and most positive force the drive can produce at speed ``xdot``.

    Returns
    -------
    (F_min, F_max) : tuple of ndarray
        Forces (N) at duty ``-32767`` and ``+32767``.
    """
    return force_from_duty(-DUTY_MAX, xdot, params), force_from_duty(DUTY_MAX, xdot, params)


def stall_force(params: ParamsLike) -> np.ndarray | float:
    """Force at full duty with the cart at rest, ``n*gear*kt*V/(R*r)`` (N)."""
    return force_from_duty(DUTY_MAX, 0.0, params)


def no_load_speed(params: ParamsLike) -> np.ndarray | float:
    """Cart speed at full duty with zero force, ``V*r/(kt*gear)`` (m/s)."""
    c = motor_constants(params)
    return c["V_supply"] * c["r_wheel"] / (c["kt"] * c["gear"])


def back_emf_damping(params: ParamsLike) -> np.ndarray | float:
    """Viscous damping the short-circuited drive adds, ``dF/dxdot = -n*(gear*kt/r)^2/R`` (N s/m)."""
    c = motor_constants(params)
    return c["n_motors"] * (c["gear"] * c["kt"] / c["r_wheel"]) ** 2 / c["R"]
