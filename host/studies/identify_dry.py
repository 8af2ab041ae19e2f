"""The dry cart of ``upright identify``'s first stage: Coulomb friction, gear play, deadband.

A geared DC-motor cart is not the linear cart of :func:`host.studies.identify_cart.cart_sim`:
it has Coulomb friction (and a breakaway force, the stiction), play in the gear between the
motor and the wheel -- with the encoder on the motor shaft, it reads the motor side of the
play -- and the H-bridge's deadband and minimum duty (docs/parameters.md, "Plant realism").
Fitted by the linear model, the play shows as lag and the dry friction as damping, and ``kt``
comes out 15-20 % low.  :func:`dry_cart_sim` is the simulators' own cart alone
(:meth:`sim.plantsim.PlantSim._integrate_real` with the pendulum's mass off, as
:class:`host.hil.virtual_robot.RobotPlant` runs it with the pendulum off): at each sub-step's
start the gear's contact (the motor side free inside the play moves at the motor's no-load
speed, pushes only against the flank it touches) and stuck / sliding are decided and held, RK4
over the sub-step, a sliding cart whose speed reverses stops and is held by static friction.
Compiled with numba (plain Python without it); tests/test_identify_dry.py checks it against
:class:`sim.plantsim.PlantSim` to rounding.

Each control tick is cut into ``substeps`` equal sub-steps and, besides, at the latency ``f``
(the previous tick's duty before it) and at the enable's edge (the coast-down), so that the
fit is continuous in both.  :func:`dry_fit` fits the duty gain (``a``, and ``D'`` through the
one motor constant), the Coulomb friction, the play, the deadband and the total lag (whole ticks
of delay plus the latency, one continuous unknown) by output error as
:func:`host.studies.identify_cart.cart_fit` does the linear ones: a global search first
(differential evolution over the physical range around the robot file's drive -- the cost is
rugged, and least squares from the robot file's values or the linear fit's ended in minima
2-9 counts rms off), then least squares from its best.  ``b`` is held (a dry cart's coast-down
stops under the Coulomb friction before ``b v`` shows).  It needs two duty levels: with one,
``a (|u| - deadband) - Coulomb`` is one number and ``kt`` came out 3-20 % off, its interval
missing the truth.  The stiction's excess over the Coulomb level is an unknown of the fit: a
cart whose drive at times stays under it sits still for those moments, which no Coulomb level
fits (0.79 mm of play, 0.017 N Coulomb, 0.25 N stiction: its truth fits to 0.32 encoder counts
and its stiction to 0.2509 N).  Where the PRBS breaks the cart loose at every reversal it does
not show (the cost is flat in it), so :func:`host.studies.identify_cart.identify_cart` still
writes it bounded only, below by the Coulomb level and above by the smallest drive force that
moved the cart.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

try:  # numba is optional: without it the same code runs as plain Python (slowly)
    from numba import njit
except ImportError:  # pragma: no cover - exercised only without numba
    def njit(*_a: Any, **_k: Any) -> Any:  # type: ignore[no-redef]
        return lambda fn: fn

from host.studies.identify_log import RunLog
from sim.plantsim import PlantSim

__all__ = ["dry_cart_sim", "dry_fit", "SUBSTEPS"]

SUBSTEPS = 8
"""Sub-steps a control tick in the fit (the simulators: 2 at the 500 Hz loop; the decisions at
each sub-step's start make the finer cut the better model of a continuous cart: a cart of
sim/uncertainty_realistic.toml with little Coulomb friction and 15 times as much stiction, logged
at 16, fits its own truth to 0.95 encoder counts rms at 8 and is refused; at 16 to 0.31, but the
fit then takes a minute and its search at 4 still lands wrong)."""
DE_ITER = 60
"""Generations of the global search (differential evolution, :data:`DE_POP` x the unknowns a generation)."""
DE_POP = 10
"""Population of the global search per unknown."""
DE_SUBSTEPS = 4
"""Sub-steps a tick in the global search (the local fit after it: ``substeps``): at 2 the search
landed in a wrong minimum at a roughest vertex of the realistic set (2.3 N of Coulomb friction for 0.5)."""
LOCAL_NFEV = 40
"""Most evaluations of the local fit after it (its Jacobian's not counted)."""
BRAKE_STARTS: tuple[float | None, ...] = (None, -1.0, 1.5, 3.0)
"""The enable's delay (ticks; None: the start's) of the local fits started from the global search's
best besides it, each with the stiction at the Coulomb level (the cost is multimodal in it)."""
PLAY_LAG_STARTS = (0.0, 1.5, 3.0)
"""Ticks of lag taken off the global search's best for the local fits started from it with 0.1 mm of
half play (the play and the lag trade places in the cost)."""
DIFF_STEP = 1e-2
"""Relative step of the fit's finite-difference Jacobian: the model is piecewise smooth (the
stuck / sliding and contact decisions at sub-step starts), a step of 1e-4 sees its steps."""


# the motor force the gear passes: the scenario simulator's own function, compiled
_gate = njit(cache=True)(PlantSim._gate)


_contact_share = njit(cache=True)(PlantSim._contact_share)
_stop = njit(cache=True)(PlantSim._stop)


@njit(cache=True)
def _acc(v: float, stuck: bool, fu: float, ce: float, eng: int, ff: float, b: float, M: float,
         share: float) -> float:
    if stuck:
        return 0.0
    g = _gate(fu - ce * v, eng)
    return ((share * g if share > 0.0 else g) - ff - b * v) / M


@njit(cache=True)
def _kernel(duty: np.ndarray, t_off: float, a: float, D: float, b: float, M: float, dt: float, f: float,
            db: float, dmin: float, fc: float, fs: float, hp: float, S: int) -> np.ndarray:
    n = duty.shape[0]
    out = np.empty(n)
    x, v, delta = 0.0, 0.0, 0.0
    fric = fs > 0.0
    stuck = fric
    dr = 1.0
    pts = np.empty(S + 3)
    for k in range(n):
        out[k] = x + delta
        m = 0
        for j in range(S + 1):
            pts[m] = j / S
            m += 1
        for c in (f, t_off - k):
            if 0.0 < c < 1.0:
                pts[m] = c
                m += 1
        for i in range(1, m):  # insertion sort of the cuts
            c = pts[i]
            j = i - 1
            while j >= 0 and pts[j] > c:
                pts[j + 1] = pts[j]
                j -= 1
            pts[j + 1] = c
        for i in range(m - 1):
            lo = pts[i]
            h = (pts[i + 1] - lo) * dt
            if h <= 0.0:
                continue
            on = (k + lo) < t_off
            u = 0.0
            if on:
                u = duty[k] if lo >= f else (duty[k - 1] if k > 0 else 0.0)
            # the bridge: minimum duty, deadband (sim.motor.bridge_fraction, in counts)
            au = abs(u)
            if au < dmin:
                au = 0.0
            au -= db
            ue = math.copysign(au if au > 0.0 else 0.0, u)
            fu = a * ue
            ce = D if on else 0.0
            if hp == 0.0:
                eng = 2
            elif delta >= hp:
                eng = 1
            elif delta <= -hp:
                eng = -1
            else:
                eng = 0
            # the motor side free in the play touches a flank within this sub-step: from the
            # contact on, it pushes (the share of the sub-step it does, the force's impulse)
            share = _contact_share(eng, delta, hp, fu / ce - v, h) if ce > 0.0 else 0.0
            if share > 0.0:
                eng = 1 if fu - ce * v > 0.0 else -1
            if fric:
                if stuck:
                    fext = _gate(fu - ce * v, eng)
                    if share > 0.0:
                        fext = share * fext  # the sub-step's push (as its integration has it)
                    if abs(fext) > fs:
                        stuck = False
                        dr = 1.0 if fext > 0.0 else -1.0
                elif v != 0.0:
                    dr = 1.0 if v > 0.0 else -1.0
            ff = fc * dr if fric else 0.0
            h2, h6 = 0.5 * h, h / 6.0
            a1 = _acc(v, stuck, fu, ce, eng, ff, b, M, share)
            v2 = v + h2 * a1
            a2 = _acc(v2, stuck, fu, ce, eng, ff, b, M, share)
            v3 = v + h2 * a2
            a3 = _acc(v3, stuck, fu, ce, eng, ff, b, M, share)
            v4 = v + h * a3
            a4 = _acc(v4, stuck, fu, ce, eng, ff, b, M, share)
            x_old, v_in = x, v
            x = x + h6 * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v = v + h6 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
            if fric and not stuck and v * dr <= 0.0:
                v, dr, stuck = _stop(v_in, v, dr, _gate(fu, eng), fc, fs, h, M)
            if hp > 0.0 and ce > 0.0:
                d = delta + h * (fu / ce) - (x - x_old)
                delta = hp if d > hp else (-hp if d < -hp else d)
    return out


def dry_cart_sim(duty: np.ndarray, driven: np.ndarray, a: float, D: float, b: float, M: float, dt: float, *,
                 f: float = 0.0, brake: float = 0.0, deadband: float = 0.0, duty_min: float = 0.0,
                 coulomb: float = 0.0, stiction: float = 0.0, backlash: float = 0.0,
                 substeps: int = SUBSTEPS) -> np.ndarray:
    """Encoder-side positions of the dry cart alone at each tick (start at rest, ``x = 0``, the play centred).

    Parameters
    ----------
    duty, driven : ndarray
        The duty (counts) of each tick and whether the bridge is enabled (one driven ->
        coasting edge at most: :func:`host.studies.identify_cart.cart_sim`).
    a, D, b : float
        Duty -> force gain (N per count), back-EMF damping ``D'`` and viscous friction (N s/m).
    M, dt : float
        Cart mass (kg), control period (s).
    f, brake : float
        Read-to-drive latency and the enable's delay after the disarm (ticks).
    deadband, duty_min : float
        The bridge's deadband and minimum duty (counts).
    coulomb, stiction : float
        Sliding and breakaway friction (N; a stiction below the Coulomb level is the Coulomb level).
    backlash : float
        Total gear play (m of cart travel); the encoder reads the motor side.
    substeps : int
        Equal sub-steps a tick (cut further at ``f`` and at the enable's edge).

    Returns
    -------
    ndarray
        ``x[k]``: the encoder's position (m) at tick ``k``, before its duty acts.
    """
    dr = np.asarray(driven, dtype=bool)
    off = np.flatnonzero(~dr)
    t_off = (float(off[0]) + f + brake) if len(off) else math.inf
    return _kernel(np.ascontiguousarray(duty, dtype=np.float64), t_off, float(a), float(D), float(b), float(M),
                   float(dt), float(f), float(deadband), float(duty_min), float(coulomb),
                   float(max(stiction, coulomb)), 0.5 * float(backlash), int(substeps))


# scaled unknowns: a (1e-3 N per count), D' (10 N s/m), b, Coulomb (N), half play (mm),
# deadband (100 counts), latency f and brake (ticks), the stiction's excess over the Coulomb level (N)
_SC = np.array([1e-3, 10.0, 1.0, 1.0, 1e-3, 100.0, 1.0, 1.0, 1.0])
_LO = np.array([1e-6, 1e-3, 0.0, 0.0, 0.0, 0.0, 0.0, -1.5, 0.0])
_HI = np.array([1e3, 1e3, 10.0, 20.0, 20.0, 100.0, 1.0, 3.0, 20.0])
N_UNK = len(_SC)


def _sq(r: np.ndarray) -> float:
    return float(r @ r)


def dry_fit(logs: Sequence[RunLog], M: float, dt: float, d: int, start: dict[str, float], *,
            one_constant: tuple[float, float] | None = None, duty_min: float = 0.0, half: int | None = None,
            fit_deadband: bool = True, fit_b: bool = False, fit_stiction: bool = True,
            substeps: int = SUBSTEPS) -> dict[str, Any]:
    """Output-error fit of the dry cart (:func:`dry_cart_sim`) to cart-only runs at whole delay ``d``.

    Parameters
    ----------
    logs : sequence of RunLog
        Cart-only runs, each with a coast-down (the Coulomb friction is told from ``b`` there).
    M, dt : float
        Cart mass (kg, known), control period (s).
    d : int
        The largest whole-tick sensor delay: the total lag ``tau`` (whole ticks of delay plus
        the latency) is fitted continuously in ``[0, d + 1)``.
    start : dict
        Initial values ``a, D, b, f, brake, deadband`` (the robot file's drive; ``f`` the total
        lag in ticks, a linear fit's), ``deadband`` in
        counts; with ``coulomb`` and ``hp`` (half play, m) too, a fit from there alone (else a few starts).
    one_constant : (float, float), optional
        ``D' = cd (a / ca)^2`` (:func:`host.studies.identify_cart.cart_fit`); else ``D'`` free.
    duty_min : float
        The bridge's minimum duty (counts), held (a PRBS of one amplitude does not see it).
    fit_deadband : bool
        Fit the deadband (two duty levels or more: with one, ``a (|u| - deadband)`` is one
        number, and ``b`` takes up the back-EMF damping the one motor constant would tie to
        ``a``); else held at ``start``'s.
    fit_b : bool
        Fit the viscous friction ``b``; default held at ``start``'s (the robot file's): on a dry
        cart the coast-down ends within tens of milliseconds under the Coulomb friction, where
        ``b v`` is a hundredth of it -- ``b`` is not in the log, and fitted it wanders off,
        taking the back-EMF damping and with it ``kt`` along.
    fit_stiction : bool
        Fit the breakaway force's excess over the Coulomb level (``stiction_ex``, N); else held
        at ``start``'s (0 without it: the stiction is the Coulomb level).  A cart whose PRBS
        breaks it loose at every reversal does not show it (the cost is flat in it: the estimate
        stays near the start); one whose drive at times stays under it sits still for those bits,
        which no Coulomb level can fit.
    half : int, optional
        The split-half checks of :func:`host.studies.identify_cart.cart_fit` (0, 1: that half of
        the driven rows and the coast-down; 2: the driven rows and the coast-down's first half).
    substeps : int
        :func:`dry_cart_sim`'s sub-steps a tick.

    Returns
    -------
    dict
        ``a, D, b, f, brake, deadband`` (counts), ``coulomb`` (N), ``backlash`` (m, total play),
        ``tau`` (the total lag, ticks) = ``d`` (whole) + ``f``, ``stiction`` (N, the breakaway
        force: the Coulomb level plus ``stiction_ex``), ``cov_full`` (of the 9 unknowns
        ``a, D, b, coulomb, backlash, deadband, f, brake, stiction_ex`` in that order, SI /
        counts), ``sse``, ``n``.
    """
    from scipy.optimize import least_squares

    # the total lag tau = d + f is one continuous unknown (the whole ticks d shift the
    # measurement, f the duty within a tick): every log's residual over its first n - dmax rows
    dmax = int(d)
    data = []
    for lg in logs:
        n = len(lg.x) - dmax
        dr = ~lg.coast[:n]
        m_ = None
        if half is not None:
            on, off = np.flatnonzero(dr), np.flatnonzero(~dr)
            mid = on[len(on) // 2] if len(on) else 0
            m_ = ~dr.copy()
            if half == 0:
                m_[:mid] = True
            elif half == 1:
                m_[mid:] |= dr[mid:]
            else:
                m_ = dr.copy()
                m_[off[:len(off) // 2]] = True
        data.append((np.asarray(lg.duty, dtype=float), ~lg.coast, lg.x, n, m_))
    free = np.array([True, one_constant is None, fit_b, True, True, fit_deadband, True, True, fit_stiction])

    def full(th: np.ndarray) -> np.ndarray:
        x = x_hold.copy()
        x[free] = th
        if one_constant is not None:
            ca, cd = one_constant
            x[1] = cd * (x[0] * _SC[0] / ca) ** 2 / _SC[1]
        return x

    def res(th: np.ndarray) -> np.ndarray:
        a, D, b, fc, hp, db, tau, br, ex = full(th) * _SC
        dd = min(int(math.floor(tau)), dmax)
        f = tau - dd
        out = []
        for du, dr, xm, n, m_ in data:
            r = xm[dd:dd + n] - dry_cart_sim(du[:n], dr[:n], a, D, b, M, dt, f=f, brake=br, deadband=db,
                                             duty_min=duty_min, coulomb=fc, stiction=fc + ex, backlash=2.0 * hp,
                                             substeps=substeps)
            if m_ is not None:
                r = r[m_]
            out.append(r - r.mean())
        return np.concatenate(out)

    x0 = np.array([start["a"], start["D"], start["b"], start.get("coulomb", 0.1), start.get("hp", 0.5e-3),
                   start["deadband"], start["f"], start["brake"], start.get("stiction_ex", 0.0)]) / _SC
    x_hold = x0.copy()
    hi_all = _HI.copy()
    hi_all[6] = dmax + 0.999
    lo_, hi_ = _LO[free], hi_all[free]
    x0 = np.clip(x0, _LO + 1e-9, hi_all - 1e-9)
    if "hp" not in start:
        # the global search (the cost is rugged: the play, the stuck / sliding switches and the
        # lag trade places): differential evolution over the physical range at DE_SUBSTEPS
        # sub-steps a tick, then the local fits below
        from scipy.optimize import differential_evolution

        sub = substeps
        substeps = DE_SUBSTEPS
        box = np.column_stack([_LO, hi_all])
        box[0] = (0.7 * x0[0], 1.3 * x0[0])  # the drive: the robot file's +-30 %
        box[1] = (0.25 * x0[1], 4.0 * x0[1])
        box[3] = (0.0, 3.0)  # N of Coulomb friction
        box[4] = (0.0, 5.0)  # mm of half play
        box[5] = (0.0, 0.1 * 32767 / _SC[5])  # deadband: 10 % of full duty
        box[8] = (0.0, 3.0)  # N of stiction beyond the Coulomb level
        de = differential_evolution(lambda th: _sq(res(th)), box[free],
                                    popsize=DE_POP, maxiter=DE_ITER, tol=1e-6, seed=0, polish=False, init="sobol")
        substeps = sub
        x0 = x_hold.copy()
        x0[free] = de.x
        # local fits from the search's best and from it with the stiction at the Coulomb level and
        # the brake at each of BRAKE_STARTS: the search at times settles where a high breakaway and
        # a late brake trade places (a cart of the commission bench, 0.79 mm of play, 0.25 N of
        # stiction: 0.90 encoder counts rms from the search's best, 0.50 from a brake of -1 tick;
        # its truth fits to 0.32)
        starts = [x0]
        for dtau in PLAY_LAG_STARTS:
            # little play, less lag: the search at times takes the lag for play (a bench cart,
            # 0.25 mm of play: 4.7 mm and 2.7 ticks more lag, 1.9 encoder counts rms; 0.28 from here)
            x1 = x0.copy()
            x1[4], x1[6], x1[8] = 0.1e-3 / _SC[4], x0[6] - dtau, 0.0
            starts.append(np.clip(x1, _LO + 1e-9, hi_all - 1e-9))
        for br in BRAKE_STARTS:
            x1 = x0.copy()
            x1[7], x1[8] = (x_hold[7] if br is None else br), 0.0
            starts.append(np.clip(x1, _LO + 1e-9, hi_all - 1e-9))
    else:
        starts = [x0]
    best = min((least_squares(res, s_[free], bounds=(lo_, hi_), x_scale="jac", diff_step=DIFF_STEP,
                              max_nfev=LOCAL_NFEV) for s_ in starts), key=lambda r_: float(r_.cost))
    r = best.fun
    k = int(np.count_nonzero(free))
    s2 = float(r @ r) / max(1, len(r) - k)
    rr = r - r.mean()
    den = float(rr @ rr) or 1.0
    rho = [float(rr[:-j] @ rr[j:]) / den for j in range(1, min(100, len(rr) // 4))]
    infl = max(1.0, 1.0 + 2.0 * sum(rho))
    J = best.jac
    cov = np.zeros((N_UNK, N_UNK))
    idx = np.flatnonzero(free)
    cov[np.ix_(idx, idx)] = infl * s2 * np.linalg.pinv(J.T @ J)
    cov *= np.outer(_SC, _SC)
    th = full(best.x) * _SC
    if one_constant is not None:
        gD = 2.0 * one_constant[1] * th[0] / one_constant[0] ** 2
        cov[1, :] = gD * cov[0, :]
        cov[:, 1] = gD * cov[:, 0]
        cov[1, 1] = gD * gD * cov[0, 0]
    # the play in m of total travel (twice the half play fitted)
    cov[4, :] *= 2.0
    cov[:, 4] *= 2.0
    tau = float(th[6])
    dd = min(int(math.floor(tau)), dmax)
    return {"a": float(th[0]), "D": float(th[1]), "b": float(th[2]), "coulomb": float(th[3]),
            "backlash": float(2.0 * th[4]), "deadband": float(th[5]), "f": tau - dd, "d": dd, "tau": tau,
            "brake": float(th[7]), "stiction_ex": float(th[8]), "stiction": float(th[3] + th[8]),
            "hp": float(th[4]), "cov_full": cov, "cov": cov[:3, :3], "sse": float(r @ r) / len(r), "n": len(r),
            "has_coast": True, "model": "dry"}
