"""Catch mode: a second, more aggressive force row for large tilts (issue 15 item 3).

The shipped tracking design (:data:`host.design.discrete.Q_DEFAULT`, clamp at ``A_CMD_DEFAULT`` (4.73 m/s^2)
from upright) cannot recover from 0.3 rad: holding 0.3 rad alone takes g tan 0.3 = 3 m/s^2,
and its position loop spends the clamp's remaining authority on the cart.  A design that
weighs the tilt far above the cart position recovers, but is too slow on a reference step
(``docs/parameters.md``).  The firmware therefore carries both rows and switches between
them (``firmware/controller.py``, ``Controller.schedule``):

* **shared**: the Kalman filter of the delayed state, the predictor over the stored forces
  and the forces themselves -- only the state-feedback row ``u = -K_c xh + kr_c r`` and its
  clamp change, so the switch is a compare and a pointer swap;
* **enter** when the a-priori estimate of the (delayed) tilt exceeds ``phi_on``;
* **hand back** only once ``|phi| < phi_off`` and ``|phidot| < w_off`` (hysteresis), from
  the reference that makes the tracking row give the catch row's force on the same
  estimator state (accepted only if they then differ by at most ``du`` newtons: bumpless
  transfer); that reference then moves to the set one at ``r_rate`` m/s (the cart's
  gentle return).

The catch row is an LQR on the same discrete plant with ``Q_CATCH``/``R_CATCH`` and a
clamp ``A_CATCH`` m/s^2 from upright (:func:`host.design.discrete.force_clamp`): the cart
acceleration the report allows is 5 m/s^2 and ``atan(5/g)`` = 0.47 rad is the largest tilt
that can be held at all, so the clamp sits just under it.  :func:`catch_rows` and
:func:`catch_clamp` give the row and its clamp that :func:`host.design.export.export` turns into
the firmware's integer entries (``CATCH``, ``KFC``, ``KBC``, ``KRC``, ``KIC``, ``SKC``).

``atan(5/g)`` ignores the drive, though: its back-EMF leaves no force at 1.8 m/s, and the
track ends at 1.25 m.  :func:`drive_bound` computes the largest tilt at rest that *any*
controller can right within all three (0.372 rad for the report's robot; 0.388 with either
the track or the drive's limits dropped), :func:`max_effort` the maneuver that does it and
:func:`direct_search` checks by direct optimisation that no acceleration profile does better.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
import control as ct
import numpy as np

from scipy.optimize import brentq

from host.design.discrete import DiscreteController, force_clamp
from sim.motor import back_emf_damping, no_load_speed, stall_force
from sim.params import RobotParams
from sim.plant import force_for_xddot, phiddot_given_xddot, xddot_affine

__all__ = ["CatchDesign", "CATCH_DEFAULT", "catch_gain", "catch_rows", "catch_clamp", "design_summary", "physical_bound",
           "TRACK_FAULT", "DriveBound", "drive_bound", "max_effort", "direct_search"]

# chosen by a random search (300 designs, weights log-uniform, clamp 4.3-4.5 m/s^2, hand-back
# thresholds and ramp speed) with the firmware in the loop (host/bench/catch.py): tilt_0p3
# settles in 1.59 s at 4.70 m/s^2 (1.82 s, 4.69 m/s^2 with the robust tracking design shipped since), the
# largest recoverable tilt is 0.334 rad (the cart's travel
# and the drive's 1.8 m/s limit it), the soft_pendulum plant is caught too (2.57 s, 4.74 m/s^2)
Q_CATCH = (0.035, 0.83, 0.41, 0.013)
R_CATCH = 0.027
A_CATCH = 4.4  # m/s^2: the catch row's acceleration clamp (the back-EMF compensation adds up to ~0.3)


@dataclass(frozen=True)
class CatchDesign:
    """Weights, clamp and switching rule of the catch row.

    Attributes
    ----------
    Q : tuple of 4 float
        Diagonal continuous LQR state weight (x, xdot, phi, phidot).
    R : float
        Continuous input weight.
    a_cmd : float
        Force clamp as cart acceleration from upright (m/s^2).
    phi_on, phi_off : float
        Tilt (rad) above which catch mode starts and below which the hand-back may happen.
    du : float
        Largest force difference (N) between the two rows accepted at the hand-back.
    w_off : float
        Tilt rate (rad/s) below which the hand-back may happen (with ``|phi| < phi_off``).
    r_rate : float
        Speed (m/s) at which the tracking row's reference moves from where the hand-back
        started it (the reference that makes both rows agree) to the set reference.
    """

    Q: tuple[float, ...] = Q_CATCH
    R: float = R_CATCH
    a_cmd: float = A_CATCH
    phi_on: float = 0.2
    phi_off: float = 0.12
    du: float = 0.05
    r_rate: float = 0.05
    w_off: float = 0.4

    def __post_init__(self) -> None:
        if len(self.Q) != 4 or any(not (q >= 0 and math.isfinite(q)) for q in self.Q) or not self.R > 0:
            raise ValueError(f"Q must be 4 non-negative weights and R > 0, got Q={self.Q}, R={self.R}")
        if not (0 < self.phi_off <= self.phi_on < math.pi / 2):
            raise ValueError(f"need 0 < phi_off <= phi_on < pi/2, got {self.phi_off}, {self.phi_on}")
        if not (self.a_cmd > 0 and self.du >= 0 and self.r_rate > 0 and self.w_off > 0):
            raise ValueError(f"a_cmd must be > 0 and du >= 0, got {self.a_cmd}, {self.du}")


CATCH_DEFAULT = CatchDesign()


def physical_bound(params: RobotParams) -> float:
    """Largest tilt (rad) a cart limited to ``params.a_max`` can hold at rest: ``atan(a_max / g)``."""
    return math.atan(float(params.a_max) / float(params.physical["g"]))


def catch_gain(ctrl: DiscreteController, design: CatchDesign = CATCH_DEFAULT) -> np.ndarray:
    """The catch row's discrete state feedback ``K_c`` (1, 4) on the controller's own plant.

    ``dlqr(Ad, Bd, Q Ts, R Ts)`` with the same mapping of continuous weights as
    :func:`host.design.discrete.controller_ss`.
    """
    Ad, Bd, Ts = ctrl.Ad, ctrl.Bd, ctrl.Ts
    K, _, _ = ct.dlqr(Ad, Bd, np.diag(np.asarray(design.Q, dtype=float)) * Ts, np.array([[design.R * Ts]]))
    K = np.asarray(K, dtype=float).reshape(1, 4)
    if np.max(np.abs(np.linalg.eigvals(Ad - Bd @ K))) >= 1.0:
        raise ValueError("the catch feedback does not stabilise the discrete plant")
    return K


def catch_rows(ctrl: DiscreteController, design: CatchDesign = CATCH_DEFAULT) -> tuple[np.ndarray, np.ndarray, float]:
    """``(Kf_c, kb_c, kr_c)``: the catch row in the firmware's structured form.

    ``u = -Kf_c xf - kb_c . b + kr_c r`` with ``Kf_c = K_c Ad^d``, ``kb_c[i] = K_c Ad^(d-1-i) Bd``
    and ``kr_c`` the unit-DC-gain precompensator of ``K_c``.
    """
    K = catch_gain(ctrl, design)
    Ad, Bd, d = ctrl.Ad, ctrl.Bd, ctrl.delay_steps
    Kf = (K @ np.linalg.matrix_power(Ad, d))[0]
    kb = np.array([(K @ np.linalg.matrix_power(Ad, d - 1 - i) @ Bd)[0, 0] for i in range(d)])
    cx = np.array([[1.0, 0.0, 0.0, 0.0]])
    kr = float(1.0 / (cx @ np.linalg.solve(np.eye(4) - Ad + Bd @ K, Bd))[0, 0])
    return Kf, kb, kr


def catch_clamp(params: RobotParams, design: CatchDesign = CATCH_DEFAULT) -> float:
    """The catch row's force clamp (N): ``design.a_cmd`` of cart acceleration from upright."""
    return force_clamp(params, design.a_cmd)


def design_summary(params: RobotParams, ctrl: DiscreteController, design: CatchDesign = CATCH_DEFAULT) -> dict[str, object]:
    """The catch row in SI units, for reports: K, kr, clamp, thresholds."""
    K = catch_gain(ctrl, design)
    _, _, kr = catch_rows(ctrl, design)
    return {"Q": list(design.Q), "R": design.R, "K": [float(v) for v in K[0]], "kr": kr,
            "u_max": catch_clamp(params, design), "a_cmd": design.a_cmd, "phi_on": design.phi_on,
            "phi_off": design.phi_off, "du": design.du}


# --- the drive-limited bound (issue 15 item 3): the largest tilt any controller can right -------

TRACK_FAULT = 1.25
"""The firmware trips ``F_TRACK`` at 1.25 x the reference limit ``loop.track`` (``firmware/app.py``):
a catch may use the track up to there, so :func:`drive_bound` lets it too."""

_HALF_PI = 0.5 * math.pi


@dataclass(frozen=True)
class _Cart:
    # the constants of the cart-pendulum (sim/plant.py) and its drive (sim/motor.py), SI units
    Mm: float  # M + m
    J: float  # I + m L^2: pendulum inertia about the pivot
    mL: float
    b: float
    g: float
    w0: float  # sqrt(m g L / J): the free pendulum's rate of fall near upright (1/s)
    a_max: float
    f_stall: float  # drive force at full duty, cart at rest (N)
    damping: float  # back-EMF: drive force lost per m/s of cart speed (N s/m)
    drive: bool  # False: the drive's limits dropped, only |xddot| <= a_max remains


def _cart(params: RobotParams, a_max: float, drive: bool) -> _Cart:
    ph = params.physical
    J = ph["I"] + ph["m"] * ph["L"] ** 2
    mL = ph["m"] * ph["L"]
    return _Cart(ph["M"] + ph["m"], J, mL, ph["b"], ph["g"], math.sqrt(mL * ph["g"] / J), float(a_max),
                 float(stall_force(params)), float(back_emf_damping(params)), drive)


def _accel_range(k: _Cart, v: float, phi: float, w: float) -> tuple[float, float]:
    # the cart accelerations the drive can give at this state -- full duty either way at the
    # cart's speed, F = +-F_stall - damping v (sim.motor.force_from_duty) -- within +-a_max.
    # The plant's xddot = (J (F - b v - mL w^2 sin) + mL cos m g L sin) / det rises with F
    if not k.drive:
        return -k.a_max, k.a_max
    a0, gain = xddot_affine(v, w, math.sin(phi), math.cos(phi), k.Mm, k.mL, k.J, k.b, k.g)
    return max(a0 - gain * (k.f_stall + k.damping * v), -k.a_max), min(a0 + gain * (k.f_stall - k.damping * v), k.a_max)


def _accel(k: _Cart, s: tuple[float, ...], mode: int, v_cap: float) -> float:
    # the cart acceleration of the family: mode -1 pushes toward -x as hard as allowed but holds
    # the speed at v_cap (a stiff speed loop, 5 ms, so RK4 sees no jump), +1 brakes as hard as
    # allowed, 0 holds the cart (a = 0)
    lo, hi = _accel_range(k, s[1], s[2], s[3])
    if mode < 0:
        return min(max(lo, -200.0 * (s[1] + v_cap)), hi) if math.isfinite(v_cap) else lo
    return hi if mode > 0 else min(max(0.0, lo), hi)


def _rhs(k: _Cart, s: tuple[float, ...], mode: int, v_cap: float) -> tuple[float, ...]:
    # the tilt sees only the cart's acceleration: J phiddot = m g L sin(phi) + m L cos(phi) xddot
    # (sim/plant.py's second equation), so the acceleration is the input here
    a = _accel(k, s, mode, v_cap)
    return s[1], a, s[3], phiddot_given_xddot(a, math.sin(s[2]), math.cos(s[2]), k.mL, k.J, k.g)


def _rk4(k: _Cart, s: tuple[float, ...], mode: int, h: float, v_cap: float = math.inf) -> tuple[float, ...]:
    k1 = _rhs(k, s, mode, v_cap)
    k2 = _rhs(k, tuple(a + 0.5 * h * d for a, d in zip(s, k1)), mode, v_cap)
    k3 = _rhs(k, tuple(a + 0.5 * h * d for a, d in zip(s, k2)), mode, v_cap)
    k4 = _rhs(k, tuple(a + h * d for a, d in zip(s, k3)), mode, v_cap)
    return tuple(a + h / 6.0 * (d1 + 2.0 * d2 + 2.0 * d3 + d4) for a, d1, d2, d3, d4 in zip(s, k1, k2, k3, k4))


def _fall(k: _Cart, phi: float, w: float) -> float:
    # the free pendulum's unstable coordinate 2 sin(phi/2) + phidot/w0: zero exactly on the
    # separatrix into upright (J w^2 / 2 = m g L (1 - cos phi), moving toward 0); positive when,
    # the cart held still, the pendulum falls toward +phi, negative toward -phi
    return 2.0 * math.sin(0.5 * phi) + w / k.w0


def _push(k: _Cart, phi0: float, h: float, x_lim: float, v_cap: float, t_cap: float) -> list[tuple[float, ...]]:
    # the push from phi0 at rest, a state every h s while the cart is in the track and the
    # pendulum above the horizontal
    s: tuple[float, ...] = (0.0, 0.0, float(phi0), 0.0)
    out = [s]
    for _ in range(int(t_cap / h)):
        s = _rk4(k, s, -1, h, v_cap)
        if abs(s[0]) > x_lim or abs(s[2]) >= _HALF_PI:
            break
        out.append(s)
    return out


def _brake(k: _Cart, s: tuple[float, ...], h: float, t_cap: float = 3.0) -> tuple[float, float, float]:
    # brake as hard as allowed from s until the cart stops: (fall coordinate, x, time) at the
    # stop, interpolated within the last step; +-inf if the pendulum passes the horizontal first
    for j in range(int(t_cap / h)):
        if s[1] >= 0.0:
            return _fall(k, s[2], s[3]), s[0], j * h
        n = _rk4(k, s, 1, h)
        if n[1] >= 0.0:
            fr = -s[1] / (n[1] - s[1])
            e = tuple(a + fr * (b - a) for a, b in zip(s, n))
            return _fall(k, e[2], e[3]), e[0], (j + fr) * h
        if abs(n[2]) >= _HALF_PI:
            return math.copysign(math.inf, n[2]), n[0], (j + 1) * h
        s = n
    return math.nan, s[0], t_cap


@dataclass(frozen=True)
class _Catch:
    ok: bool
    t_brake: float = math.nan  # s: the switch from push to brake
    t_stop: float = math.nan  # s: the cart stops with the pendulum on the separatrix
    x_stop: float = math.nan  # m: where (the far end of the cart's travel)
    v_peak: float = math.nan  # m/s


def _catch(k: _Cart, phi0: float, h: float, x_lim: float, v_cap: float = math.inf, t_cap: float = 4.0) -> _Catch:
    # does the push-brake family (the push holding v_cap once there) right phi0 within the
    # track (see drive_bound)?
    S = _push(k, phi0, h, x_lim, v_cap, t_cap)
    if not math.isfinite(x_lim):
        # no track: once the pendulum is on the separatrix the cart stops pushing and rolls on
        # at its speed (no braking ever needed) while the pendulum rises into upright
        for i, s in enumerate(S):
            if _fall(k, s[2], s[3]) <= 0.0:
                return _Catch(True, i * h, math.nan, math.nan, max(abs(q[1]) for q in S[: i + 1]))
        return _Catch(False)

    def shot(t: float) -> tuple[float, float, float]:
        i = min(int(t / h), len(S) - 1)
        s = S[i] if t - i * h <= 0.0 else _rk4(k, S[i], -1, t - i * h, v_cap)
        return _brake(k, s, h)

    # the first switch time whose brake ends on the separatrix; braking later overshoots it at
    # the price of more track.  Scan every ~10 ms, then solve within the bracket
    step = max(1, int(round(0.01 / h)))
    grid = list(range(0, len(S), step))
    if grid[-1] != len(S) - 1:
        grid.append(len(S) - 1)
    z_prev = shot(0.0)[0]
    for a, b in zip(grid, grid[1:]):
        z_b = shot(b * h)[0]
        if z_prev > 0.0 >= z_b:
            t_b = float(brentq(lambda t: max(min(shot(t)[0], 1e3), -1e3), a * h, b * h, xtol=1e-7))
            _, x_stop, dt = shot(t_b)
            i = min(int(t_b / h), len(S) - 1)
            return _Catch(abs(x_stop) <= x_lim, t_b, t_b + dt, x_stop, max(abs(q[1]) for q in S[: i + 1]))
        z_prev = z_b
    return _Catch(False)


def _largest(k: _Cart, x_lim: float, h: float, tol: float) -> tuple[float, _Catch]:
    # bisection for the largest phi0 the family rights; above atan(a_max/g) not even a_max
    # toward -x stops the fall (phiddot > 0 throughout), so the search starts below it
    lo, hi = 0.0, math.atan(k.a_max / k.g)
    best = _Catch(True)
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        c = _catch(k, mid, h, x_lim)
        if c.ok:
            lo, best = mid, c
        else:
            hi = mid
    return lo, best


@dataclass(frozen=True)
class DriveBound:
    """The largest tilt at rest any controller can right on this robot (:func:`drive_bound`).

    Attributes
    ----------
    phi_max : float
        The bound (rad): the track, the drive (supply, back-EMF) and ``|xddot| <= a_max``.
    phi_max_no_track : float
        Without the track (an endless one): the drive and ``a_max`` only.
    phi_max_no_speed_limit : float
        Without the drive's limits (any force at any speed): the track and ``a_max`` only.
    phi_max_a_only : float
        Neither track nor drive: ``a_max`` alone; equals ``atan(a_max / g)``
        (:func:`physical_bound`) to the tolerance, a check of the computation.
    v_max : float
        The drive's no-load speed ``V r / (kt gear)`` (m/s): the cart cannot go faster.
    x_lim : float
        Half-length of the track allowed (m), the cart starting at its centre.
    a_max : float
        Cart acceleration limit (m/s^2).
    t_brake, t_stop, x_stop, v_peak : float
        The maneuver that rights ``phi_max``: the switch from push to brake (s), the time (s)
        and place (m) the cart stops, its top speed (m/s).
    """

    phi_max: float
    phi_max_no_track: float
    phi_max_no_speed_limit: float
    phi_max_a_only: float
    v_max: float
    x_lim: float
    a_max: float
    t_brake: float
    t_stop: float
    x_stop: float
    v_peak: float


def drive_bound(params: RobotParams, *, a_max: float | None = None, x_lim: float | None = None, h: float = 2e-3,
                tol: float = 1e-4) -> DriveBound:
    """The largest tilt at rest from which any controller can right the pendulum (issue 15 item 3).

    **Rights** means: the cart, started at rest at the track's centre, ends at rest with the
    pendulum on the separatrix into upright, ``2 sin(phi/2) + phidot/w0 = 0`` with
    ``w0 = sqrt(m g L / (I + m L^2))`` -- the free pendulum's stable manifold of the upright
    equilibrium, from which the cart held still (``xddot = 0``, within every limit) lets it
    rise into upright -- without the cart leaving ``|x| <= x_lim`` on the way, on
    :mod:`sim.plant`'s nonlinear plant with :mod:`sim.motor`'s drive.  Any controller that
    balances the robot at rest must get there (the upright equilibrium lies on that manifold
    and the cart must stop on the track), so no controller does better than this.

    **Admissible** at every instant: a duty in [-1, 1] of the supply, whose force at the cart's
    speed is ``d F_stall - c v`` (the back-EMF ``c v`` leaves no forward force at the no-load
    speed ``v_max``), and ``|xddot| <= a_max``.  Relaxed in the controller's favour: no sensor
    delay, exact state, continuous time (no 2 ms sampling, no duty quantisation), and the
    track up to where the firmware faults (``TRACK_FAULT * loop.track`` = 1.25 m, not the
    usable 1.0 m).

    **Computed** with the push-brake family: the cart accelerates toward the fall as hard as
    allowed (``a_max``, then what the drive still gives near ``v_max``), then brakes as hard as
    allowed until it stops; the switch time is solved so the stop lands on the separatrix
    (braking later only overshoots it, at the price of more track), and a bisection over the
    tilt finds the largest one whose stop lies in the track.  That family is the optimum:

    * in the linearised plant the pendulum's unstable mode ends at zero only if
      ``int exp(-w0 t) xddot(t) dt = -g phi0 / w0``, a linear programme in ``xddot`` whose
      optimum under ``|xddot| <= a_max``, ``|v| <= v_max``, a bounded track and the cart at rest
      at the end is bang-(hold at the top speed)-bang with the braking as late as the track
      allows -- what the family does;
    * on the nonlinear plant, :func:`direct_search` (SLSQP over free piecewise-constant
      acceleration profiles, no switching structure imposed) finds nothing above it: 0.37235
      rad (24 intervals, 4 starts) against this 0.37238 for the report's robot, 0.38782
      against 0.38781 without the drive's limits; holding the speed below ``v_max`` before
      braking (``max_effort(..., v_cap=)``, 1.0 to 1.75 m/s from 0.37 rad) only costs track.

    On an endless track (``phi_max_no_track``) the cart need not stop: it stops pushing once
    the pendulum is on the separatrix and rolls on at its speed (the drive overcomes the
    friction below ``v_max``) while the pendulum rises, then can slow down as gently as it
    likes.

    Parameters
    ----------
    params : RobotParams
        The robot (``sim.params.load_params()``: the report's).
    a_max : float, optional
        Cart acceleration limit (m/s^2); default ``params.a_max``.
    x_lim : float, optional
        Half-length of the track (m); default ``TRACK_FAULT * params.track``; ``inf``: none.
    h : float
        RK4 step (s).
    tol : float
        Bisection tolerance on the tilt (rad): each figure is the largest tilt found to
        right, at most ``tol`` under the exact one.

    Returns
    -------
    DriveBound
        The bound, the bounds with the track or the drive's limits dropped (which constraint
        binds), the drive's speed limit and the maneuver at the bound.
    """
    a = float(params.a_max) if a_max is None else float(a_max)
    xl = TRACK_FAULT * float(params.track) if x_lim is None else float(x_lim)
    if not (a > 0 and xl > 0):
        raise ValueError(f"a_max and x_lim must be > 0, got {a}, {xl}")
    k, free = _cart(params, a, True), _cart(params, a, False)
    phi, c = _largest(k, xl, h, tol)
    return DriveBound(phi, _largest(k, math.inf, h, tol)[0], _largest(free, xl, h, tol)[0],
                      _largest(free, math.inf, h, tol)[0], float(no_load_speed(params)), xl, a,
                      c.t_brake, c.t_stop, c.x_stop, c.v_peak)


def max_effort(params: RobotParams, phi0: float, *, a_max: float | None = None, x_lim: float | None = None,
               drive: bool = True, v_cap: float = math.inf, hold: float = 0.5, h: float = 2e-3) -> dict[str, np.ndarray]:
    """The push-brake maneuver of :func:`drive_bound` from ``phi0`` at rest, logged every ``h`` s.

    Push toward the fall as hard as allowed (holding the speed at ``v_cap`` once there), brake
    as hard as allowed from the switch time that stops the cart on the separatrix into upright,
    then hold the cart still for ``hold`` s while the pendulum rises.

    Parameters
    ----------
    params : RobotParams
        The robot.
    phi0 : float
        Initial tilt (rad), positive (the cart moves toward ``-x``).
    a_max, x_lim : float, optional
        As in :func:`drive_bound`.
    drive : bool
        False drops the drive's limits (only ``|xddot| <= a_max``).
    v_cap : float
        Speed (m/s) held once reached during the push (``inf``: none).
    hold : float
        Time (s) the cart is held still after it stops.
    h : float
        RK4 step and log period (s).

    Returns
    -------
    dict
        Arrays ``t, x, xdot, phi, phidot, xddot`` (the state and the cart acceleration at
        each sample), ``force`` (N, what the plant needs for that acceleration) and ``duty``
        (the drive's duty in [-1, 1] that gives it at the cart's speed; nan without the drive's
        limits), and the scalars ``t_brake``, ``t_stop`` (s), ``x_stop`` (m), ``ok`` (1.0 when the
        stop lies in the track).

    Raises
    ------
    ValueError
        If no switch time stops the cart on the separatrix (the tilt is beyond even an
        endless track).
    """
    a = float(params.a_max) if a_max is None else float(a_max)
    xl = TRACK_FAULT * float(params.track) if x_lim is None else float(x_lim)
    k = _cart(params, a, drive)
    c = _catch(k, float(phi0), h, 1e9, v_cap)  # the whole maneuver, in the track or not
    if math.isnan(c.t_brake) or math.isnan(c.t_stop):
        raise ValueError(f"no push-brake maneuver rights {phi0} rad")
    s: tuple[float, ...] = (0.0, 0.0, float(phi0), 0.0)
    rows, t = [], 0.0
    # push (the last step shortened to land on the switch), brake to the stop, hold
    for mode, until in ((-1, c.t_brake), (1, c.t_stop), (0, c.t_stop + hold)):
        while t < until - 1e-12:
            rows.append((t, *s, _accel(k, s, mode, v_cap)))
            dt = min(h, until - t)
            s = _rk4(k, s, mode, dt, v_cap)
            t += dt
    rows.append((t, *s, _accel(k, s, 0, v_cap)))
    R = np.array(rows)
    tt, x, v, phi, w, acc = R.T
    force = force_for_xddot(acc, v, w, np.sin(phi), np.cos(phi), k.Mm, k.mL, k.J, k.b, k.g)
    duty = (force + k.damping * v) / k.f_stall if drive else np.full_like(force, np.nan)
    return {"t": tt, "x": x, "xdot": v, "phi": phi, "phidot": w, "xddot": acc, "force": force, "duty": duty,
            "t_brake": np.float64(c.t_brake), "t_stop": np.float64(c.t_stop), "x_stop": np.float64(c.x_stop),
            "ok": np.float64(abs(c.x_stop) <= xl)}


def _rhs_batch(k: _Cart, s: np.ndarray, u: np.ndarray) -> np.ndarray:
    # _rhs over a batch of states s (4, K) with free efforts u (K,) in [-1, 1] spanning the
    # admissible accelerations (-1: hardest toward -x, +1: hardest toward +x)
    v, phi, w = s[1], s[2], s[3]
    sn, c = np.sin(phi), np.cos(phi)
    if k.drive:
        a0, gain = xddot_affine(v, w, sn, c, k.Mm, k.mL, k.J, k.b, k.g)
        lo = np.maximum(a0 - gain * (k.f_stall + k.damping * v), -k.a_max)
        hi = np.minimum(a0 + gain * (k.f_stall - k.damping * v), k.a_max)
    else:
        lo, hi = np.full_like(v, -k.a_max), np.full_like(v, k.a_max)
    a = lo + 0.5 * (u + 1.0) * (hi - lo)
    return np.array([v, a, w, phiddot_given_xddot(a, sn, c, k.mL, k.J, k.g)])


def _rollout(k: _Cart, P: np.ndarray, n: int, steps: int) -> tuple[np.ndarray, np.ndarray]:
    # columns of P: (phi0, T, u_1..u_n); the cart positions and tilts at every RK4 node
    # (2, n steps, K) and the end states (4, K)
    K = P.shape[1]
    s = np.zeros((4, K))
    s[2] = P[0]
    h = P[1] / (n * steps)
    xs = np.empty((2, n * steps, K))
    for j in range(n):
        u = np.clip(P[2 + j], -1.0, 1.0)
        for r in range(steps):
            k1 = _rhs_batch(k, s, u)
            k2 = _rhs_batch(k, s + 0.5 * h * k1, u)
            k3 = _rhs_batch(k, s + 0.5 * h * k2, u)
            k4 = _rhs_batch(k, s + h * k3, u)
            s = s + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
            xs[:, j * steps + r] = s[0], s[2]
    return xs, s


def direct_search(params: RobotParams, *, a_max: float | None = None, x_lim: float | None = None, n: int = 24,
                  steps: int = 4, starts: int = 3, seed: int = 0, drive: bool = True) -> float:
    """The largest tilt a free acceleration profile rights, by direct optimisation: a check of :func:`drive_bound`.

    Maximises ``phi0`` over ``n`` piecewise-constant efforts ``u_j`` in [-1, 1] (each spans the
    accelerations admissible at the current state, as in :func:`drive_bound`: ``-1`` the hardest
    toward ``-x``, ``+1`` toward ``+x``) and the duration ``T``, subject to the same end
    condition (the cart at rest on the separatrix into upright at ``T``) and ``|x| <= x_lim`` at
    every RK4 node, with SLSQP from ``starts`` starting profiles (a crude push-then-brake,
    all-zero, then seeded random ones).  No switching structure is imposed, so a result above
    ``drive_bound(...).phi_max`` would show the push-brake family is not the best; being a local
    method on a coarse profile it only ever finds less than the true optimum.

    Parameters
    ----------
    params : RobotParams
        The robot.
    a_max, x_lim : float, optional
        As in :func:`drive_bound` (``x_lim`` finite).
    n, steps : int
        Effort intervals and RK4 steps per interval.
    starts : int
        Starting profiles.
    seed : int
        Seed of the random starting profiles.
    drive : bool
        False drops the drive's limits (only ``|xddot| <= a_max``).

    Returns
    -------
    float
        The best ``phi0`` (rad) found that meets the end condition to 1e-4 and the track to 1e-4 m.
    """
    from scipy.optimize import minimize

    a = float(params.a_max) if a_max is None else float(a_max)
    xl = TRACK_FAULT * float(params.track) if x_lim is None else float(x_lim)
    if not (a > 0 and 0 < xl < math.inf and n >= 2 and steps >= 1):
        raise ValueError(f"need a_max > 0, a finite x_lim > 0, n >= 2, steps >= 1; got {a}, {xl}, {n}, {steps}")
    k = _cart(params, a, drive)
    m = n + 2
    eps = 1e-6
    cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def values(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # (constraint values, their Jacobian) from one batch: p and its m forward perturbations
        key = p.tobytes()
        if key not in cache:
            P = np.repeat(p[:, None], m + 1, axis=1)
            P[np.arange(m), np.arange(m) + 1] += eps
            (xs, ps), e = _rollout(k, P, n, steps)
            z = 2.0 * np.sin(0.5 * e[2]) + e[3] / k.w0
            # the pendulum stays above the horizontal (a full turn would also end with z = 0)
            G = np.vstack([e[1], z, xl - xs, xl + xs, _HALF_PI - ps, _HALF_PI + ps])
            g = G[:, 0].copy()
            cache.clear()
            cache[key] = (g, ((G[:, 1:] - G[:, :1]) / eps))
        return cache[key]

    unit = np.eye(m)[0]
    bounds = [(0.0, math.atan(a / k.g)), (0.2, 3.0)] + [(-1.0, 1.0)] * n
    cons = [{"type": "eq", "fun": lambda p: values(p)[0][:2], "jac": lambda p: values(p)[1][:2]},
            {"type": "ineq", "fun": lambda p: values(p)[0][2:], "jac": lambda p: values(p)[1][2:]}]
    rng = np.random.default_rng(seed)
    best = 0.0
    for i in range(starts):
        if i == 0:
            u0 = np.where(np.arange(n) < n // 2, -1.0, 1.0)
        elif i == 1:
            u0 = np.zeros(n)
        else:
            u0 = rng.uniform(-1.0, 1.0, n)
        p0 = np.concatenate([[0.3, 1.0], u0])
        res = minimize(lambda p: -p[0], p0, jac=lambda p: -unit, method="SLSQP", bounds=bounds,
                       constraints=cons, options={"maxiter": 300, "ftol": 1e-9})
        g = values(res.x)[0]
        if np.all(np.abs(g[:2]) <= 1e-4) and np.all(g[2:] >= -1e-4):
            best = max(best, float(res.x[0]))
    return best
