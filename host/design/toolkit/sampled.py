"""The discrete-time steps of the toolkit: ZOH plant, dlqr, placement at exp(s Ts), the discrete
observer and Kalman gains, the firmware-structured controller with the delay (re-exported by
:mod:`host.design.toolkit`)."""

from __future__ import annotations

import math
from typing import Sequence

import control as ct
import numpy as np

from host.design.discrete import DiscreteController, controller_ss
from host.design.toolkit.core import Observer, StateFeedback, _noise, _poles, _weights, plant, precompensator
from sim.params import RobotParams

__all__ = ["discrete_plant", "dlqr", "dplace", "dobserver", "dkalman", "discrete_observer_controller"]


def discrete_plant(params: RobotParams, rate: float) -> ct.StateSpace:
    """``control.c2d(plant(params), 1/rate, "zoh")``."""
    return ct.c2d(plant(params), 1.0 / rate, method="zoh")


def dlqr(params: RobotParams, Q: Sequence[float] | np.ndarray, R: float, rate: float) -> StateFeedback:
    """Discrete LQR on the ZOH plant with the continuous weights mapped as ``Q Ts``, ``R Ts``."""
    Gd = discrete_plant(params, rate)
    q, r = _weights(Q, R)
    Ts = 1.0 / rate
    K, _, E = ct.dlqr(Gd.A, Gd.B, q * Ts, r * Ts)
    K = np.asarray(K, float).ravel()
    return StateFeedback(K=K, Nbar=precompensator(Gd.A, Gd.B, K, Ts), poles=np.asarray(E), Ts=Ts)


def dplace(params: RobotParams, poles: Sequence[complex], rate: float) -> StateFeedback:
    """Discrete pole placement at ``exp(poles Ts)``."""
    Gd = discrete_plant(params, rate)
    Ts = 1.0 / rate
    p = np.exp(_poles(poles, 4, "poles") * Ts)
    K = np.asarray(ct.place(Gd.A, Gd.B, p), float).ravel()
    return StateFeedback(K=K, Nbar=precompensator(Gd.A, Gd.B, K, Ts),
                         poles=np.linalg.eigvals(Gd.A - Gd.B @ K[None, :]), Ts=Ts)


def dobserver(params: RobotParams, poles: Sequence[complex], rate: float) -> Observer:
    """Discrete (predictor) observer gain at ``exp(poles Ts)``: ``place(Ad.T, C.T, .).T``."""
    Gd = discrete_plant(params, rate)
    Ts = 1.0 / rate
    p = np.exp(_poles(poles, 4, "observer poles") * Ts)
    L = np.asarray(ct.place(Gd.A.T, Gd.C.T, p), float).T
    return Observer(L=L, poles=np.linalg.eigvals(Gd.A - L @ Gd.C), Ts=Ts)


def dkalman(params: RobotParams, sigma_force: float, sigma_meas: Sequence[float], rate: float) -> Observer:
    """Discrete Kalman gain, ``control.dlqe(Ad, Bd, C, QN, RN)`` (per-sample variances)."""
    Gd = discrete_plant(params, rate)
    QN, RN = _noise(sigma_force, sigma_meas)
    L, _, E = ct.dlqe(Gd.A, Gd.B, Gd.C, QN, RN)
    return Observer(L=np.asarray(L, float), poles=np.asarray(E), Ts=1.0 / rate)


def discrete_observer_controller(params: RobotParams, K: Sequence[float], Ld: np.ndarray, rate: float,
                                 delay: float = 0.0, u_max: float = math.inf) -> DiscreteController:
    """The firmware's controller structure (:func:`host.design.discrete.controller_ss`: filter on the
    delayed measurement, predictor over the stored inputs, ``u = -K xh + kr r``) with a chosen
    full-order estimator: the predictor gain ``Ld`` (:func:`dobserver`, :func:`dkalman`) becomes the
    filter gain ``M = Ad^-1 Ld`` (the same error poles, ``Ad (I - M C) = Ad - Ld C``)."""
    c = controller_ss(params, rate, delay, design="gain", K=K, u_max=u_max)
    M = np.linalg.solve(c.Ad, np.asarray(Ld, float))
    I_MC = np.eye(4) - M @ c.C
    c.Ac[:4, :4] = c.Ad @ I_MC
    c.Bc[:4, :2] = c.Ad @ M
    c.Cc[0, :4] = -(c.Kf @ I_MC)[0]
    c.Dc[0, :2] = -(c.Kf @ M)[0]
    c.M = M
    return c
