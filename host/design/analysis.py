"""Analysis of the linearised plant: transfer functions, poles and zeros, controllability
and observability (the report's section 2).

Everything is computed from :func:`sim.plant.linear_model`, itself built from the
physical parameters, so one TOML file drives every number printed here.
"""

from __future__ import annotations

from dataclasses import dataclass

import control as ct
import numpy as np
import scipy.linalg as sla

from sim.params import RobotParams
from sim.plant import linear_model, reduced_model

__all__ = [
    "clean_tf",
    "transfer_functions",
    "controllability",
    "observability_rank",
    "observability_gramian",
    "single_sensor_observability",
    "SensorObservability",
]


def clean_tf(tf: ct.TransferFunction, tol: float = 1e-9) -> ct.TransferFunction:
    """Remove numerically spurious terms from a SISO transfer function.

    Coefficients smaller than ``tol`` times the largest one are zeroed, common roots at
    the origin cancelled (``ss2tf`` leaves ``1e-16 s^k`` terms and an ``s/s`` pair), and
    the denominator made monic.

    Parameters
    ----------
    tf : control.TransferFunction
        SISO transfer function.
    tol : float
        Relative size below which a coefficient is treated as zero.

    Returns
    -------
    control.TransferFunction
    """
    num = np.atleast_1d(np.squeeze(tf.num[0][0])).astype(float)
    den = np.atleast_1d(np.squeeze(tf.den[0][0])).astype(float)
    num = np.where(np.abs(num) < tol * np.abs(num).max(), 0.0, num)
    den = np.where(np.abs(den) < tol * np.abs(den).max(), 0.0, den)
    num, den = np.trim_zeros(num, "f"), np.trim_zeros(den, "f")
    # cancel common factors of s (trailing zeros of both polynomials)
    while len(num) > 1 and len(den) > 1 and num[-1] == 0.0 and den[-1] == 0.0:
        num, den = num[:-1], den[:-1]
    lead = den[0]
    return ct.tf(num / lead, den / lead)


def transfer_functions(params: RobotParams) -> dict[str, ct.TransferFunction]:
    """Transfer functions from cart force to angle and to cart position (eqs. 2.11-2.12).

    Parameters
    ----------
    params : RobotParams

    Returns
    -------
    dict
        ``{"phi": P_phi(s), "x": P_x(s)}``, cleaned with :func:`clean_tf`.
    """
    A, B, C, D = linear_model(params)
    sys = ct.ss(A, B, C, D)
    full = ct.ss2tf(sys)
    return {"x": clean_tf(full[0, 0]), "phi": clean_tf(full[1, 0])}


def controllability(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, float, int]:
    """Controllability matrix ``Wr``, its determinant (single input) and rank.

    Returns
    -------
    Wr : ndarray
    det : float
        ``det(Wr)`` (``nan`` if ``Wr`` is not square).
    rank : int
    """
    Wr = ct.ctrb(A, B)
    det = float(np.linalg.det(Wr)) if Wr.shape[0] == Wr.shape[1] else float("nan")
    return Wr, det, int(np.linalg.matrix_rank(Wr))


def observability_rank(A: np.ndarray, C: np.ndarray) -> int:
    """Rank of the observability matrix ``Wo`` of ``(A, C)``."""
    return int(np.linalg.matrix_rank(ct.obsv(A, np.atleast_2d(C))))


def observability_gramian(A: np.ndarray, C: np.ndarray, horizon: float) -> np.ndarray:
    """Finite-horizon observability Gramian ``Wo(T) = int_0^T e^(A't) C'C e^(At) dt``.

    Valid for unstable systems (the infinite-horizon Gramian that MATLAB's
    ``gram(sys, 'o')`` computes exists only for stable ones).  Computed exactly with Van
    Loan's block matrix exponential.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    C : ndarray, shape (p, n)
    horizon : float
        ``T`` in seconds, positive.

    Returns
    -------
    ndarray, shape (n, n)
    """
    if horizon <= 0:
        raise ValueError("horizon must be positive")
    A = np.asarray(A, float)
    C = np.atleast_2d(np.asarray(C, float))
    n = A.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -A.T
    M[:n, n:] = C.T @ C
    M[n:, n:] = A
    E = sla.expm(M * horizon)
    F22 = E[n:, n:]
    G12 = E[:n, n:]
    W = F22.T @ G12
    return 0.5 * (W + W.T)


@dataclass(frozen=True)
class SensorObservability:
    """How well one sensor observes a model.

    Attributes
    ----------
    model : str
        ``"full"`` (4 states) or ``"reduced"`` (3 states, x dropped).
    sensor : str
        Measured state variable.
    rank : int
        Rank of the observability matrix.
    observable : bool
    volume : float
        ``det(Wo(T))`` of the finite-horizon Gramian: the squared volume of the
        observability ellipsoid; larger means the initial state is easier to estimate.
    min_singular : float
        Smallest eigenvalue of ``Wo(T)``: the energy of the least observable direction.
    """

    model: str
    sensor: str
    rank: int
    observable: bool
    volume: float
    min_singular: float


def single_sensor_observability(params: RobotParams, horizon: float = 1.0) -> list[SensorObservability]:
    """Which single sensor makes the plant observable, and how well (the report's §2.6).

    Parameters
    ----------
    params : RobotParams
    horizon : float
        Horizon (s) of the observability Gramian.

    Returns
    -------
    list of SensorObservability
        For the full model with sensors x, phi and the reduced model with xdot, phi,
        phidot.
    """
    A, _, _, _ = linear_model(params)
    Ar, _ = reduced_model(params)
    out = []
    cases = [
        ("full", A, "x", 0),
        ("full", A, "phi", 2),
        ("reduced", Ar, "xdot", 0),
        ("reduced", Ar, "phi", 1),
        ("reduced", Ar, "phidot", 2),
    ]
    for model, AA, name, idx in cases:
        C = np.zeros((1, AA.shape[0]))
        C[0, idx] = 1.0
        rank = observability_rank(AA, C)
        W = observability_gramian(AA, C, horizon)
        ev = np.linalg.eigvalsh(W)
        out.append(
            SensorObservability(
                model=model,
                sensor=name,
                rank=rank,
                observable=rank == AA.shape[0],
                volume=float(np.linalg.det(W)),
                min_singular=float(max(ev.min(), 0.0)),
            )
        )
    return out
