"""The controllers of the design report, computed from the physical parameters.

Time domain (report §3): pole placement from an overshoot/settling specification, LQR
(with the weight search the report ran in MATLAB), a Luenberger observer 10x faster than
the controller, the reference precompensator ``kr`` and the report's PID.
Frequency domain (report §4): ``C(s) = K (s+z1)(s+z2)/s`` on the angle, its Nyquist
encirclement count, the critical gain, stability margins and the gang of four.

Sign convention: state feedback is ``u = -K x + kr r`` (python-control's ``place`` and
``lqr`` return ``K`` in that convention), output feedback is ``u = -C(s) phi``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import control as ct
import numpy as np

from host.design.analysis import clean_tf, transfer_functions
from sim.metrics import settling_time
from sim.params import RobotParams
from sim.plant import linear_model, simulate

__all__ = [
    "REPORT_PLACE_POLES",
    "REPORT_LQR_Q",
    "REPORT_LQR_R",
    "REPORT_PID",
    "zeta_omega_from_spec",
    "dominant_poles",
    "place_gain",
    "lqr_gain",
    "observer_gain",
    "precompensator",
    "Constraints",
    "StepScore",
    "score_state_feedback",
    "lqr_weight_search",
    "pid_tf",
    "loop_controller",
    "LoopAnalysis",
    "gang_of_four",
    "analyse_loop",
    "critical_gain",
    "make_controller",
]

# The report's choices, kept here once.
REPORT_PLACE_POLES = (-4.774 + 5.9172j, -4.774 - 5.9172j, -10.1, -10.2)
# Q was lost from the report's text; these weights reproduce its K to < 1e-6 (docs/parameters.md).
REPORT_LQR_Q = (5.4, 0.0, 0.8, 0.0)
REPORT_LQR_R = 0.001
REPORT_PID = (79.95, 125.40, 8.24)  # Kp, Ki, Kd on the angle
REPORT_OBSERVER_POLES = (-47.74, -48.74, -49.74, -50.74)
REPORT_LOOP = (20.0, 1.0, 10.0)  # K, z1, z2 of the final C(s) = K (s+z1)(s+z2)/s
DERIVATIVE_FILTER = 100.0  # rad/s, roll-off that makes PID and C(s) proper (Simulink's N)


def zeta_omega_from_spec(overshoot: float, settling: float) -> tuple[float, float]:
    """Damping and natural frequency from a step specification (report eq. 3.7).

    Parameters
    ----------
    overshoot : float
        Peak overshoot as a fraction (0.08 for 8 %), in (0, 1).
    settling : float
        2 % settling time (s), using ``Ts = 4 / (zeta omega)``.

    Returns
    -------
    zeta, omega : float
    """
    if not 0.0 < overshoot < 1.0:
        raise ValueError(f"overshoot must be a fraction in (0, 1), got {overshoot!r}")
    if settling <= 0:
        raise ValueError(f"settling time must be positive, got {settling!r}")
    ln = math.log(overshoot)
    zeta = -ln / math.sqrt(math.pi**2 + ln**2)
    return zeta, 4.0 / (zeta * settling)


def dominant_poles(zeta: float, omega: float, extra: Sequence[float] = (2.1, 2.14)) -> np.ndarray:
    """Closed-loop poles: a dominant pair plus real poles ``extra`` times deeper.

    Parameters
    ----------
    zeta, omega : float
        Damping and natural frequency of the dominant pair.
    extra : sequence of float
        Factors (> 1) applied to the dominant real part for the remaining poles.

    Returns
    -------
    ndarray of complex
    """
    sigma = zeta * omega
    wd = omega * math.sqrt(max(1.0 - zeta**2, 0.0))
    return np.array([-sigma + 1j * wd, -sigma - 1j * wd] + [-sigma * f for f in extra])


def place_gain(params: RobotParams, poles: Sequence[complex] = REPORT_PLACE_POLES) -> np.ndarray:
    """State-feedback gain placing the closed-loop poles (report §3.2).

    Returns
    -------
    ndarray, shape (4,)
    """
    A, B, _, _ = linear_model(params)
    return np.asarray(ct.place(A, B, list(poles))).ravel()


def lqr_gain(
    params: RobotParams, q: Sequence[float] = REPORT_LQR_Q, r: float = REPORT_LQR_R
) -> np.ndarray:
    """LQR state-feedback gain for ``Q = diag(q)``, ``R = r`` (report §3.2.c).

    Returns
    -------
    ndarray, shape (4,)
    """
    if r <= 0 or any(v < 0 for v in q):
        raise ValueError("LQR weights must be non-negative and R positive")
    A, B, _, _ = linear_model(params)
    K, _, _ = ct.lqr(A, B, np.diag(q), np.array([[r]]))
    return np.asarray(K).ravel()


def observer_gain(
    params: RobotParams, K: np.ndarray | None = None, factor: float = 10.0, poles: Sequence[float] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Luenberger observer gain for the measurements ``[x, phi]`` (report §3.5).

    The observer poles are ``factor`` times the slowest closed-loop real part, spread by
    1 rad/s (the report's [-47.74, -48.74, -49.74, -50.74] for its pole-placement design),
    unless ``poles`` is given.

    Returns
    -------
    L : ndarray, shape (4, 2)
    poles : ndarray
    """
    A, B, C, _ = linear_model(params)
    if poles is None:
        if K is None:
            raise ValueError("give the controller gain K or the observer poles")
        cl = np.linalg.eigvals(A - B @ np.atleast_2d(K))
        sigma = factor * float(np.min(np.abs(cl.real)))
        poles = [-(sigma + i) for i in range(4)]
    L = np.asarray(ct.place(A.T, C.T, list(poles))).T
    return L, np.asarray(poles, dtype=complex)


def precompensator(params: RobotParams, K: np.ndarray) -> float:
    """Reference gain ``kr`` so the cart position follows a constant reference (eq. 3.14).

    ``kr = -1 / (Cr (A - B K)^-1 B)`` with ``Cr`` selecting the cart position.
    """
    A, B, _, _ = linear_model(params)
    Cr = np.array([[1.0, 0.0, 0.0, 0.0]])
    Acl = A - B @ np.atleast_2d(K)
    return float(-1.0 / (Cr @ np.linalg.solve(Acl, B))[0, 0])


# --- scoring against the report's constraints ---------------------------------------


@dataclass(frozen=True)
class Constraints:
    """The report's design constraints (§3.1), from the ``[loop]`` table by default."""

    phi_max: float = 0.3
    t_settle: float = 2.5
    a_max: float = 5.0

    @classmethod
    def from_params(cls, params: RobotParams) -> "Constraints":
        """Read the constraints from the parameter file."""
        return cls(phi_max=params.phi_max, t_settle=params.t_settle, a_max=params.a_max)


@dataclass(frozen=True)
class StepScore:
    """Metrics of a closed-loop response and whether it meets :class:`Constraints`."""

    peak_phi: float
    settling: float
    peak_accel: float
    peak_force: float
    ok: bool
    checks: dict[str, bool] = field(default_factory=dict)


def _settled(ts: float) -> float:
    return math.inf if math.isnan(ts) else ts


def score_state_feedback(
    params: RobotParams,
    K: np.ndarray,
    *,
    step: float = 0.2,
    phi0: float = 0.0,
    duration: float = 5.0,
    constraints: Constraints | None = None,
) -> StepScore:
    """Simulate the nonlinear plant under ``u = -K x + kr r`` for a cart-position step.

    Parameters
    ----------
    params : RobotParams
    K : ndarray, shape (4,)
    step : float
        Reference step of the cart position (m), applied at t = 0.
    phi0 : float
        Initial tilt (rad).
    duration : float
        Simulated time (s).
    constraints : Constraints, optional
        Defaults to the parameter file's.

    Returns
    -------
    StepScore
    """
    cons = constraints or Constraints.from_params(params)
    K = np.asarray(K, float).ravel()
    kr = precompensator(params, K)
    res = simulate(params, [0.0, 0.0, phi0, 0.0], duration, controller=lambda t, x: -K @ x + kr * step, dt=2e-3, substeps=2)
    t = res["t"]
    accel = np.gradient(res["xdot"], t)
    peak_phi = float(np.max(np.abs(res["phi"])))
    # 2 % band; a response still outside it at the end never settles (inf)
    ts_x = _settled(settling_time(t, res["x"], final=step, scale=max(abs(step), 0.05)))
    ts_phi = _settled(settling_time(t, res["phi"], final=0.0, scale=max(peak_phi, 1e-3)))
    ts = max(ts_x, ts_phi) if step else ts_phi
    checks = {
        "phi": peak_phi < cons.phi_max,
        "settling": ts < cons.t_settle,
        "accel": float(np.max(np.abs(accel))) <= cons.a_max,
    }
    return StepScore(
        peak_phi=peak_phi,
        settling=ts,
        peak_accel=float(np.max(np.abs(accel))),
        peak_force=float(np.max(np.abs(res["force"]))),
        ok=all(checks.values()),
        checks=checks,
    )


def lqr_weight_search(
    params: RobotParams,
    q_x: Sequence[float] = (0.05, 0.1, 0.2, 0.3, 0.5, 1.0, 5.4),
    q_phi: Sequence[float] = (0.1, 0.8, 5.0, 20.0),
    r: float = REPORT_LQR_R,
    step: float = 0.2,
) -> list[tuple[tuple[float, float], StepScore]]:
    """Grid search over the LQR weights on x and phi, scored against the constraints.

    The report ran this search exhaustively in MATLAB; here each candidate is simulated
    on the nonlinear plant for a cart-position step and checked against
    |phi| < phi_max, settling < t_settle and |xddot| <= a_max.

    Returns
    -------
    list of ((q_x, q_phi), StepScore)
        Sorted best first: candidates meeting every constraint, fastest settling first.
    """
    out = []
    for qx in q_x:
        for qp in q_phi:
            K = lqr_gain(params, (qx, 0.0, qp, 0.0), r)
            out.append(((qx, qp), score_state_feedback(params, K, step=step)))
    out.sort(key=lambda item: (not item[1].ok, item[1].settling, item[1].peak_accel))
    return out


# --- output feedback on the angle ------------------------------------------------------


def pid_tf(gains: Sequence[float] = REPORT_PID, n: float = DERIVATIVE_FILTER) -> ct.TransferFunction:
    """PID on the angle, ``Kp + Ki/s + Kd s/(1 + s/n)`` (Simulink's filtered derivative)."""
    kp, ki, kd = gains
    s = ct.tf("s")
    return kp + ki / s + kd * s / (1 + s / n)


def loop_controller(k: float, z1: float, z2: float, rolloff: float | None = None) -> ct.TransferFunction:
    """The report's loop-shaping controller ``C(s) = k (s+z1)(s+z2)/s``.

    ``rolloff`` (rad/s) adds a pole pair factor ``1/(1+s/rolloff)`` so the controller is
    proper and can be discretised; ``None`` keeps the report's improper form.
    """
    s = ct.tf("s")
    C = k * (s + z1) * (s + z2) / s
    if rolloff:
        C = C / (1 + s / rolloff)
    return C


def _encirclements(L: ct.TransferFunction) -> int:
    resp = ct.nyquist_response(L, omega_num=4000, warn_encirclements=False, warn_nyquist=False)
    return int(resp.count)


@dataclass
class LoopAnalysis:
    """Frequency-domain analysis of ``L = P C`` closed with negative feedback.

    Attributes
    ----------
    open_loop_rhp : int
        P: open-loop poles of L in the right half plane.
    encirclements : int
        N: net clockwise encirclements of -1 by the Nyquist curve (python-control's count).
    closed_loop_rhp : int
        Z = N + P, cross-checked against the closed-loop poles.
    stable : bool
    gain_margin, phase_margin, wg, wp : float
        From :func:`control.stability_margins`.
    gang : dict
        For each of S, T, PS, CS: ``{"stable": bool, "proper": bool, "peak": float,
        "poles_at_origin": int}``.
    ms, mt : float
        Peak sensitivity and complementary sensitivity.
    """

    open_loop_rhp: int
    encirclements: int
    closed_loop_rhp: int
    stable: bool
    gain_margin: float
    phase_margin: float
    wg: float
    wp: float
    gang: dict[str, dict[str, float | bool | int]]
    ms: float
    mt: float


def _peak(sys: ct.TransferFunction, omega: np.ndarray) -> float:
    mag = np.abs(sys(1j * omega))
    return float(np.max(mag))


def gang_of_four(P: ct.TransferFunction, C: ct.TransferFunction) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Numerator and denominator polynomials of S, T, PS and CS, nothing cancelled.

    All four share the unreduced characteristic polynomial ``den(P) den(C) + num(P) num(C)``,
    so a pole-zero cancellation between plant and controller stays visible.

    Returns
    -------
    dict
        ``{"S": (num, den), "T": ..., "PS": ..., "CS": ...}``, highest power first.
    """
    pn, pd = np.squeeze(P.num[0][0]), np.squeeze(P.den[0][0])
    cn, cd = np.squeeze(C.num[0][0]), np.squeeze(C.den[0][0])
    char = np.polyadd(np.polymul(pd, cd), np.polymul(pn, cn))
    return {
        "S": (np.polymul(pd, cd), char),
        "T": (np.polymul(pn, cn), char),
        "PS": (np.polymul(pn, cd), char),
        "CS": (np.polymul(cn, pd), char),
    }


def analyse_loop(params: RobotParams, C: ct.TransferFunction) -> LoopAnalysis:
    """Nyquist count, margins and the gang of four for ``C`` on the angle loop.

    The gang of four is formed from the numerator/denominator polynomials without
    cancelling anything, so a pole-zero cancellation between plant and controller (the
    controller's integrator against the plant's zero at s = 0) shows up as a pole at
    the origin of the function that keeps it.
    """
    P = transfer_functions(params)["phi"]
    L = clean_tf(ct.minreal(P * C, verbose=False))
    ol_rhp = int(np.sum(np.real(L.poles()) > 1e-9))
    N = _encirclements(L)
    Z = N + ol_rhp
    funcs = gang_of_four(P, C)
    omega = np.logspace(-3, 4, 3000)
    gang: dict[str, dict[str, float | bool | int]] = {}
    for name, (num, den) in funcs.items():
        tf = ct.tf(num, den)
        red = ct.minreal(tf, verbose=False)
        poles = red.poles()
        at0 = int(np.sum(np.abs(poles) < 1e-6))
        gang[name] = {
            "stable": bool(np.all(np.real(poles) < -1e-9)),
            "proper": len(np.trim_zeros(np.atleast_1d(num), "f")) <= len(np.trim_zeros(np.atleast_1d(den), "f")),
            "peak": _peak(tf, omega),
            "poles_at_origin": at0,
        }
    gm, pm, wg, wp = ct.stability_margins(L)[:4]
    cl_rhp = int(np.sum(np.real(np.roots(np.polyadd(np.squeeze(L.den[0][0]), np.squeeze(L.num[0][0])))) > 1e-9))
    return LoopAnalysis(
        open_loop_rhp=ol_rhp,
        encirclements=N,
        closed_loop_rhp=Z if Z == cl_rhp else cl_rhp,
        stable=cl_rhp == 0,
        gain_margin=float(gm),
        phase_margin=float(pm),
        wg=float(wg),
        wp=float(wp),
        gang=gang,
        ms=float(gang["S"]["peak"]),
        mt=float(gang["T"]["peak"]),
    )


def critical_gain(params: RobotParams, C0: ct.TransferFunction, kmax: float = 1e3) -> float:
    """Smallest gain ``K`` for which ``K C0`` stabilises the angle loop (report §4.4.c).

    Found by bisection on the largest real part of the roots of ``den(L) + K num(L)``,
    with ``L = P C0`` reduced to a minimal form.

    Raises
    ------
    ValueError
        If no gain up to ``kmax`` stabilises the loop.
    """
    P = transfer_functions(params)["phi"]
    L = clean_tf(ct.minreal(P * C0, verbose=False))
    num, den = np.squeeze(L.num[0][0]), np.squeeze(L.den[0][0])

    def worst(k: float) -> float:
        return float(np.max(np.real(np.roots(np.polyadd(den, k * num)))))

    ks = np.geomspace(1e-3, kmax, 400)
    stable = [k for k in ks if worst(k) < 0]
    if not stable:
        raise ValueError("no gain up to kmax stabilises the loop")
    hi = stable[0]
    idx = int(np.searchsorted(ks, hi))
    lo = ks[idx - 1] if idx > 0 else 0.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if worst(mid) < 0 else (mid, hi)
    return float(hi)


# --- controllers for simulation ----------------------------------------------------------


def _discrete_phi_controller(C: ct.TransferFunction, dt: float) -> Callable[[float, np.ndarray], float]:
    """``u = -C(s) phi`` discretised (Tustin) at ``dt`` as a stateful callable."""
    Cd = ct.ss(ct.c2d(ct.ss(C), dt, method="tustin"))
    A, B, Cm, D = (np.asarray(M, float) for M in (Cd.A, Cd.B, Cd.C, Cd.D))
    z = np.zeros(A.shape[0])

    def ctrl(t: float, x: np.ndarray) -> float:
        nonlocal z
        e = np.array([x[2]])
        u = float((Cm @ z + D @ e)[0])
        z = A @ z + B @ e
        return -u

    return ctrl


def make_controller(
    params: RobotParams, design: str, *, reference: float = 0.0, dt: float = 1e-3
) -> Callable[[float, np.ndarray], float]:
    """A controller ``f(t, x) -> F`` for :func:`sim.plant.simulate`, by design name.

    Parameters
    ----------
    params : RobotParams
    design : {"place", "lqr", "place-observer", "lqr-observer", "pid", "loopshape"}
        State feedback uses the true state, the observer variants estimate it from
        ``[x, phi]``; ``pid`` and ``loopshape`` act on the angle only (the cart drifts).
    reference : float
        Constant cart-position reference (m) for the state-feedback designs.
    dt : float
        Sample period the callable is called at (used by the dynamic controllers).
    """
    designs = ("place", "lqr", "place-observer", "lqr-observer", "pid", "loopshape")
    if design not in designs:
        raise ValueError(f"unknown design {design!r}; choose from {', '.join(designs)}")
    if design in ("pid", "loopshape"):
        C = pid_tf() if design == "pid" else loop_controller(*REPORT_LOOP, rolloff=DERIVATIVE_FILTER)
        return _discrete_phi_controller(C, dt)
    K = place_gain(params) if design.startswith("place") else lqr_gain(params)
    kr = precompensator(params, K)
    if not design.endswith("observer"):
        return lambda t, x: float(-K @ x + kr * reference)
    A, B, C, _ = linear_model(params)
    L, _ = observer_gain(params, K)
    # observer xhat' = A xhat + B u + L (y - C xhat), discretised exactly over dt
    Ao = A - L @ C
    Bo = np.hstack([B, L])
    sysd = ct.c2d(ct.ss(Ao, Bo, np.eye(4), 0), dt)
    Ad, Bd = np.asarray(sysd.A), np.asarray(sysd.B)
    xhat = np.zeros(4)

    def ctrl(t: float, x: np.ndarray) -> float:
        nonlocal xhat
        u = float(-K @ xhat + kr * reference)
        y = C @ x
        xhat = Ad @ xhat + Bd @ np.concatenate([[u], y])
        return u

    return ctrl
