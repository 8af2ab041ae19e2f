"""The first stage of ``upright identify``: the drive and the delay from cart-only runs alone.

A cart-only run (``upright board excite --cart-only``: pendulum off or locked upright, the
firmware's PRBS on the duty open loop, then the driver off while the cart coasts) holds
everything the drive is: the cart's equation, with the duty ``u`` and the velocity ``v``,

``M dv/dt = a u_eff - D' v - b v``   driven (the H-bridge enabled),
``M dv/dt = -b v``                   coasting (the driver off: no current, no back-EMF braking),

``u_eff = sign(u) max(|u| - deadband, 0)``.  ``a`` is the duty -> force gain (the force
constant ``kt`` through the known supply, resistance, gear and wheel), ``D'`` the back-EMF
damping (``kt ke``), ``b`` the viscous friction -- separated from ``D'`` only by the
coast-down.  The deadband is separable from ``a`` only with two or more duty levels (two
cart-only runs of different amplitudes); with one it is held at the robot file's value.

**Timing.**  The board reads its sensors at the start of a tick and drives the motor when the
tick's computation is done, a fraction of a period later (0.2-0.5 of a 2 ms tick on the
emulated Pico); the sensors lag by ``sensors.delay``, whole ticks.  For a linear plant only the
sum matters: the fit's delay is ``d + f`` ticks, ``d`` whole (the grid) and ``f`` in [0, 1)
fitted -- each tick applies the previous duty for ``f`` of the period and its own for the rest.
``delay`` reported is ``d`` ticks, ``latency`` ``f`` ticks (s).  A model without ``f`` puts the
latency into the drive's time constant ``M / (D' + b)`` (11 ms on the report's robot, of the
order of the delay) and from there into ``kt`` -- the bias this stage was written to remove.

Each tick is simulated exactly (:func:`cart_sim`: piecewise-constant force on two segments per
tick, first-order velocity); the positions are fitted by output error
(``scipy.optimize.least_squares``, one offset per log).  Intervals: the Jacobian's covariance,
inflated by the residuals' autocorrelation (noise), combined in quadrature with the change of
each estimate between the fit and the same fit on each half of the excitation (a model that
does not fit moves with the data it sees: the method's bias shows there), and with
:data:`BIAS_FLOOR` of the estimate, the bias measured on the validation's realistic plants.

**Dry carts.**  A geared cart with Coulomb friction, gear play (the encoder on the motor shaft)
and a deadband is not this linear cart: fitted by it, ``kt`` came out 15-20 % low, and most such
logs leave residuals of 1-9 encoder counts (refused).  Where the linear fit leaves more than
:data:`DRY_COUNTS` and the runs have two duty levels, the dry cart of
:mod:`host.studies.identify_dry` (the simulators' own equations) is fitted and returned when it
fits better: ``model`` "dry", with ``coulomb``, ``stiction`` (bounded only) and ``backlash``
(:data:`DRY_NAMES`); ``b`` is held at the robot file's, its interval the realistic set's range.
Intervals as above (noise, split halves, ``b`` at the ends of its range, :data:`DRY_BIAS_FLOOR`).
A cart that did not move (:data:`MIN_TRAVEL_COUNTS`) is refused whatever the model.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
from scipy import signal

from host.studies.identify_log import LogError, RunLog
from sim import sensors as ssens
from sim.motor import DUTY_MAX
from sim.params import RobotParams

__all__ = ["cart_sim", "cart_fit", "identify_cart", "CART_NAMES", "CART_UNITS", "BIAS_FLOOR", "min_cart_rows",
           "drive_of", "DRY_NAMES"]

CART_NAMES = ("b", "kt", "ke", "delay", "latency", "deadband")
"""First-stage estimates: viscous friction (N s/m), force and back-EMF constants, sensor
delay (s, whole ticks), the board's read-to-drive latency (s), the bridge's deadband (fraction
of full duty; fitted only from two or more amplitudes)."""
CART_UNITS = {"b": "N*s/m", "kt": "N*m/A", "ke": "V*s/rad", "delay": "s", "latency": "s", "deadband": "1",
              "coulomb": "N", "stiction": "N", "backlash": "m"}
BIAS_FLOOR = {"b": 0.03, "kt": 0.03, "ke": 0.02, "deadband": 0.0}
"""Fraction of each estimate added (in quadrature) to its interval for the method's own bias."""
MAX_RES_COUNTS = 1.0
DRY_COUNTS = 0.5
"""A linear fit whose rms residual exceeds this many encoder counts (clean runs of a linear cart:
0.3-0.4, the quantisation's own 0.29 and the telemetry's 0.1 mm steps) is fitted again with the
dry cart (:mod:`host.studies.identify_dry`); the dry fit is the result when it fits better."""
MIN_TRAVEL_COUNTS = 20.0
"""Fewest encoder counts the cart must travel under the excitation for its drive to be identified."""
DRY_ABS_FLOOR = {"coulomb": 0.01, "backlash": 5e-5, "deadband": 5e-4}
"""Absolute floors of the dry fit's intervals (N, m, fraction of full duty), in quadrature with the
relative ones: a Coulomb friction of 0.065 N came out 0.0038 N high, outside its 5 % (bench identify_dry)."""
DRY_B_RANGE = (0.5, 2.0)
"""Factors on the robot file's ``b`` the dry fit is repeated at for its intervals (``b`` is held:
the realistic set's friction range, sim/uncertainty_realistic.toml)."""
DRY_NAMES = ("coulomb", "stiction", "backlash")
"""The dry cart's estimates besides :data:`CART_NAMES` (in the result only when it was fitted):
Coulomb friction and the breakaway force (N, ``cart.coulomb``, ``cart.stiction``), the total gear
play (m of cart travel, ``motor.backlash``)."""
DRY_BIAS_FLOOR = {"b": 0.05, "kt": 0.02, "ke": 0.02, "deadband": 0.05, "coulomb": 0.05, "backlash": 0.05}
"""The dry fit's :data:`BIAS_FLOOR`: fraction of each estimate added in quadrature for the method's bias
(the sub-step decisions of stuck / sliding and of the gear's contact)."""
"""Largest rms residual of the cart-only fit, in encoder counts (clean runs: 0.3-0.5)."""
MIN_DRIVEN_S = 1.5
"""Board seconds of excitation a cart-only log needs at least (several drive time constants of
PRBS bits: fewer fit the delay and the latency into the noise)."""
MIN_COAST_S = 2.0
"""Board seconds of coast-down needed to separate ``b`` from the back-EMF."""


def min_cart_rows(rate: float) -> tuple[int, int]:
    """Fewest driven and coasting rows of a cart-only log at ``rate`` Hz."""
    return int(math.ceil(MIN_DRIVEN_S * rate)), int(math.ceil(MIN_COAST_S * rate))


def _eff(duty: np.ndarray, db: float) -> np.ndarray:
    # the bridge's deadband (duty counts): |u| - db, never below zero
    if db <= 0.0:
        return duty
    a = np.abs(duty) - db
    return np.copysign(np.where(a > 0.0, a, 0.0), duty)


def cart_sim(duty: np.ndarray, driven: np.ndarray, a: float, D: float, b: float, M: float, dt: float,
             f: float = 0.0, deadband: float = 0.0, v0: float = 0.0, brake: float = 0.0) -> np.ndarray:
    """Positions of the cart alone (start at x = 0, speed ``v0``), exact per tick.

    Tick ``k`` applies ``duty[k - 1]`` for the first ``f`` of the period and ``duty[k]`` for
    the rest (the board's read-to-drive latency).  ``driven`` is true up to the disarm (one
    driven -> coasting edge at most, the first false row ``k0``); the H-bridge is enabled
    until ``k0 + f + brake`` ticks: ``brake`` > 0, on at the disarm's duty 0 (the motor
    shorted, braking) -- the enable's own delay; ``brake`` < 0, off during the last driven
    tick -- the disarm command handled after that tick's duty was written and reported.  ``M xdd = a u_eff - (D + b) xd`` while enabled,
    ``M xdd = -b xd`` after.  ``deadband`` in duty counts.
    """
    n = len(duty)
    u = _eff(np.asarray(duty, dtype=float), deadband)
    dr = np.asarray(driven, dtype=bool)
    off = np.flatnonzero(~dr)
    t_off = (int(off[0]) + f + brake) if len(off) else math.inf
    k = np.arange(n, dtype=float)
    c = np.clip(t_off - k, 0.0, 1.0)  # the enable's edge within each tick (1: enabled all through)
    s1, s2 = np.minimum(f, c), np.maximum(f, c)
    u_prev = np.concatenate([[0.0], u[:-1]])
    ld, lc = max((D + b) / M, 1e-9), max(b / M, 1e-9)
    v = np.empty(n + 1)
    v[0] = v0
    segs = []
    for lo, hi in ((np.zeros(n), s1), (s1, s2), (s2, np.ones(n))):
        tt = (hi - lo) * dt
        on = (k + lo) < t_off  # the segment starts with the bridge enabled
        uu = np.where(lo < f, u_prev, u)
        lam = np.where(on, ld, lc)
        e = np.exp(-lam * tt)
        w = np.where(on, a * uu, 0.0) / (lam * M)  # the segment's terminal speed
        segs.append((tt, lam, e, w))
    E = segs[0][2] * segs[1][2] * segs[2][2]
    G = np.zeros(n)
    for _, _, e, w in segs:
        G = G * e + w * (1.0 - e)
    # v[k+1] = E[k] v[k] + G[k]: a first-order filter on each run of ticks with one E
    cuts = [0, *(np.flatnonzero(np.abs(np.diff(E)) > 1e-15) + 1).tolist(), n]
    for i0, i1 in zip(cuts[:-1], cuts[1:]):
        if i1 <= i0:
            continue
        ee = E[i0]
        y, _ = signal.lfilter([1.0], [1.0, -ee], G[i0:i1], zi=[ee * v[i0]])
        v[i0 + 1:i1 + 1] = y
    vs = v[:-1].copy()
    dx = np.zeros(n)
    for tt, lam, e, w in segs:
        dx += w * tt + (vs - w) * (1.0 - e) / lam
        vs = w + (vs - w) * e
    return np.concatenate([[0.0], np.cumsum(dx)])[:n]


def _levels(carts: Sequence[RunLog]) -> int:
    # distinct duty amplitudes among the driven rows (within 10 % of each other: one level)
    amps = sorted({float(abs(u)) for lg in carts for u in np.unique(lg.duty[~lg.coast]) if u != 0})
    n, last = 0, -1.0
    for a_ in amps:
        if last <= 0 or a_ > 1.1 * last:
            n += 1
            last = a_
    return n


def _data(logs: Sequence[RunLog], d: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    out = []
    for lg in logs:
        n = len(lg.x) - d
        out.append((lg.duty[:n], ~lg.coast[:n], lg.x[d:d + n]))
    return out


def cart_fit(logs: Sequence[RunLog], M: float, dt: float, d: int, *, latency: bool = True,
             deadband: float | None = 0.0, half: int | None = None, f_hold: float = 0.0,
             brake_hold: float | None = None, one_constant: tuple[float, float] | None = None,
             driven_only: bool = False) -> dict[str, Any]:
    """Output-error fit of cart-only runs at whole delay ``d``: ``a``, ``D'``, ``b``, the latency ``f``.

    Parameters
    ----------
    logs : sequence of RunLog
        Cart-only runs.
    M : float
        Cart mass (kg), known.
    dt : float
        Control period (s).
    d : int
        Whole ticks of sensor delay (measurement ``k + d`` is the state at ``k``).
    latency : bool
        Fit ``f`` (else 0).
    deadband : float or None
        Deadband in duty counts, held; None: fitted (needs two duty levels).
    f_hold : float
        The latency (ticks) when not fitted.
    brake_hold : float, optional
        The enable's delay after the disarm (ticks) held at this value; default fitted (with a coast-down).
    one_constant : (float, float), optional
        ``(ca, cd)``: the motor's one constant ``k`` (``kt = ke``, a DC motor in SI units) gives
        ``a = ca k`` and ``D' = cd k^2`` -- ``D'`` is not a free parameter then.
    driven_only : bool
        Only the driven rows enter the residual (``b`` and the brake held at 0: the coarse
        search of the delay, which the coast-down's model cannot mislead then).
    half : int, optional
        0 or 1: only that half of each log's driven rows (and all its coast-down) enters the
        residual; 2: all driven rows and the first half of the coast-down (the split-half
        checks of the method's bias).

    Returns
    -------
    dict
        ``a, D, b, f, deadband, brake`` (``b`` NaN without a coast-down), ``cov`` (of a, D, b),
        ``sse`` (mean squared residual, m^2), ``n``.
    """
    from scipy.optimize import least_squares

    data = _data(logs, d)
    masks = []
    for _, dr, _ in data:
        if driven_only:
            masks.append(dr.copy())
            continue
        if half is None:
            masks.append(None)
            continue
        on = np.flatnonzero(dr)
        mid = on[len(on) // 2] if len(on) else 0
        m_ = ~dr.copy()
        if half == 2:
            # every driven row, the first half of the coast-down
            off = np.flatnonzero(~dr)
            m_ = dr.copy()
            m_[off[:len(off) // 2]] = True
        elif half == 0:
            m_[:mid] = True
        else:
            m_[mid:] |= dr[mid:]
        masks.append(m_)
    has_coast = any((~dr).any() for _, dr, _ in data) and not driven_only
    fit_db = deadband is None
    # scaled unknowns: a (1e-3 N per count), D' (10 N s/m), b, f, deadband (100 counts), brake (ticks)
    sc = np.array([1e-3, 10.0, 1.0, 1.0, 100.0, 1.0])
    free = [True, one_constant is None, has_coast, latency, fit_db, has_coast and brake_hold is None]

    def full(th: np.ndarray) -> np.ndarray:
        x = np.array([2.0, 4.0, 0.0, f_hold, 0.0 if fit_db else float(deadband or 0.0) / 100.0,
                      brake_hold or 0.0])
        x[np.flatnonzero(free)] = th
        if one_constant is not None:
            ca, cd = one_constant
            x[1] = cd * (x[0] * sc[0] / ca) ** 2 / sc[1]
        return x

    def res(th: np.ndarray) -> np.ndarray:
        a, D, b, f, db, br = full(th) * sc
        out = []
        for (du, dr, xm), m_ in zip(data, masks):
            r = xm - cart_sim(du, dr, a, D, b, M, dt, f=f, deadband=db, brake=br)
            if m_ is not None:
                r = r[m_]
            out.append(r - r.mean())
        return np.concatenate(out)

    x0 = np.array([2.0, 4.0, 0.1, 0.5, 1.0, 0.5])[free]
    lo = np.array([1e-6, 1e-3, 0.0, 0.0, 0.0, -1.5])[free]
    hi = np.array([1e3, 1e3, 1e3, 1.0, 50.0, 3.0])[free]
    sol = least_squares(res, x0, bounds=(lo, hi), x_scale="jac")
    r = sol.fun
    k = int(np.count_nonzero(free))
    dof = max(1, len(r) - k)
    s2 = float(r @ r) / dof
    # neighbouring residuals are correlated (quantisation, model error): the variance
    # inflated by 1 + 2 sum of the residual autocorrelation over 100 lags (clipped at 1)
    rr = r - r.mean()
    den = float(rr @ rr) or 1.0
    rho = [float(rr[:-j] @ rr[j:]) / den for j in range(1, min(100, len(rr) // 4))]
    infl = max(1.0, 1.0 + 2.0 * sum(rho))
    J = sol.jac
    covs = infl * s2 * np.linalg.pinv(J.T @ J)
    cov_full = np.zeros((6, 6))
    idx = np.flatnonzero(free)
    cov_full[np.ix_(idx, idx)] = covs
    cov_full *= np.outer(sc, sc)
    th = full(sol.x) * sc
    if one_constant is not None:
        # D' = cd (a / ca)^2: its variance and covariances through dD'/da
        gD = 2.0 * one_constant[1] * th[0] / one_constant[0] ** 2
        cov_full[1, :] = gD * cov_full[0, :]
        cov_full[:, 1] = gD * cov_full[:, 0]
        cov_full[1, 1] = gD * gD * cov_full[0, 0]
    return {"a": float(th[0]), "D": float(th[1]), "b": float(th[2]) if has_coast else math.nan,
            "f": float(th[3]), "deadband": float(th[4]), "brake": float(th[5]), "cov": cov_full[:3, :3], "cov_full": cov_full,
            "sse": float(r @ r) / len(r), "n": len(r), "has_coast": has_coast}


def drive_of(fit: dict[str, Any], params: RobotParams) -> dict[str, float]:
    """``kt`` and ``ke`` from the duty gain ``a`` and the damping ``D'`` of a fit, with the known drive."""
    v = params.values
    n, gear, r, R, V = (v["motor.n_motors"], v["motor.gear"], v["motor.r_wheel"], v["motor.R"], v["motor.V_supply"])
    kt = fit["a"] * DUTY_MAX * R * r / (n * gear * V)
    ke = fit["D"] * R * r**2 / (n * gear**2 * kt) if kt else math.nan
    return {"kt": float(kt), "ke": float(ke)}


def check_cart_log(lg: RunLog, rate: float) -> None:
    """Refuse (one line, :class:`LogError`) a cart-only log too short to identify the drive."""
    nd, nc = min_cart_rows(rate)
    driven = int(np.count_nonzero(~lg.coast))
    coast = int(np.count_nonzero(lg.coast))
    if driven < nd:
        raise LogError(lg.name, "", f"{driven / rate:.2f} s of board time excited, the drive needs at least "
                                    f"{MIN_DRIVEN_S:g} s: record again with `upright board excite --cart-only "
                                    f"--board-seconds {max(2 * MIN_DRIVEN_S, 5.0):g}`")
    if coast and coast < nc:
        raise LogError(lg.name, "", f"{coast / rate:.2f} s of coast-down, at least {MIN_COAST_S:g} s needed to "
                                    "separate the friction from the back-EMF: record again with "
                                    f"--board-coast {1.5 * MIN_COAST_S:g}")


def _coefs(params: RobotParams) -> tuple[float, float]:
    # a = ca k, D' = cd k^2 for a motor constant k (kt = ke) and the known drive
    v = params.values
    n, gear, r, R, V = (v["motor.n_motors"], v["motor.gear"], v["motor.r_wheel"], v["motor.R"], v["motor.V_supply"])
    return n * gear * V / (r * R * DUTY_MAX), n * gear**2 / (r**2 * R)


def _stage(carts: Sequence[RunLog], params: RobotParams, dmax: int, latency: bool, dbk: float | None,
           db_known: float, oc: tuple[float, float] | None) -> tuple[int, dict[str, Any], list[float]]:
    # the whole delay: a coarse fit per candidate (latency and brake held at typical values),
    # then the full fit at the best candidate and its neighbours
    M, dt = float(params.M), 1.0 / float(params.rate)
    sse = [cart_fit(carts, M, dt, d, latency=False, deadband=db_known, f_hold=0.5 if latency else 0.0,
                    one_constant=oc, driven_only=True)["sse"] for d in range(dmax + 1)]
    d0 = int(np.argmin(sse))
    fits = {d: cart_fit(carts, M, dt, d, latency=latency, deadband=dbk, one_constant=oc)
            for d in (d0 - 1, d0, d0 + 1) if 0 <= d <= dmax}
    for dd, ff in fits.items():
        sse[dd] = ff["sse"]
    d = min(fits, key=lambda k: fits[k]["sse"])
    return d, fits[d], sse


def identify_cart(logs: Sequence[RunLog], params: RobotParams, *, max_delay: float = 0.03,
                  latency: bool = True, one_constant: bool = True, dry: bool = True) -> dict[str, Any]:
    """The first stage: the drive (``kt``, ``ke``), the friction ``b``, the delay and latency from cart-only runs.

    Parameters
    ----------
    logs : sequence of RunLog
        Cart-only runs (:func:`host.studies.identify_log.read_log`), a coast-down in at least
        one for ``b``; two amplitudes or more to fit the deadband.
    params : RobotParams
        The known constants: ``cart.M`` (weighed), the drive (supply, resistance, gear, wheel,
        motor count), the loop rate; ``motor.deadband`` is held unless fitted.
    max_delay : float
        Largest whole-tick sensor delay searched (s).
    latency : bool
        Fit the read-to-drive latency (else none: the model of earlier versions).
    one_constant : bool
        The motor's force and back-EMF constants are one (``kt = ke``: a DC motor in SI units,
        and the model's ``motor.kt``): ``D'`` follows from ``a``, and the drive's time
        constant no longer competes with the delay for the same lag.  The free fit (``kt`` and
        ``ke`` apart) runs too, as a check: ``free`` in the result, and a note when its ``ke``
        differs from the one constant by more than its interval (``motor.R`` or
        ``motor.V_supply`` of ``params`` off, or not a plain DC motor).  False: the free fit is the result.
    dry : bool
        Where the linear cart does not fit (rms residual over :data:`DRY_COUNTS`) and the runs
        have two duty levels or more, fit the dry cart (:mod:`host.studies.identify_dry`:
        Coulomb friction, gear play, deadband; ``b`` held) and return it when it fits better
        (``model`` "dry", the estimates of :data:`DRY_NAMES` besides).  With one level the dry
        cart is not identifiable (``a (|u| - deadband)`` and the Coulomb friction are one number:
        fitted anyway, ``kt`` came out up to 20 % off with intervals that missed it): the linear
        result or its refusal, with a note asking for a second amplitude.  False: the linear cart only.

    Returns
    -------
    dict
        ``estimates`` {name: value} of :data:`CART_NAMES`, ``ci`` {name: [lo, hi]} (95 %),
        ``units``, ``delay_samples``, ``latency_samples`` (the two add up to the fitted total),
        ``fit_delay`` (the grid's whole delay of the chosen fit, whose ``f`` completes it),
        ``delay_sse`` (mean squared residual per whole delay, m^2), ``fit`` (the chosen
        :func:`cart_fit`), ``free`` (the free fit's ``kt``, ``ke`` and 95 % intervals),
        ``rows``, ``logs``, ``notes``.

    Raises
    ------
    LogError
        A log too short (:func:`check_cart_log`), or no cart-only log.
    """
    carts = [lg for lg in logs if lg.cart_only]
    if not carts:
        raise ValueError("identify_cart needs a cart-only run (excite mode 2)")
    rate = float(params.rate)
    dt = 1.0 / rate
    for lg in carts:
        check_cart_log(lg, rate)
    M = float(params.M)
    fit_db = _levels(carts) >= 2
    db_known = float(params.values.get("motor.deadband", 0.0) or 0.0) * DUTY_MAX
    dmax = int(round(max_delay / dt))
    dbk = None if fit_db else db_known
    oc = _coefs(params) if one_constant else None
    d, cf, sse = _stage(carts, params, dmax, latency, dbk, db_known, oc)
    count = 1.0 / float(ssens.enc_counts_per_m(params))
    moved = max(float(np.ptp(lg.x[~lg.coast])) if (~lg.coast).any() else 0.0 for lg in carts)
    if moved < MIN_TRAVEL_COUNTS * count:
        # a cart that did not move fits any drive: nothing to identify (a stuck cart, a dead
        # drive, an amplitude inside the deadband or under the breakaway force)
        raise LogError(", ".join(lg.name for lg in carts), "x",
                       f"the cart moved {moved / count:.0f} encoder counts under the excitation (at least "
                       f"{MIN_TRAVEL_COUNTS:g} needed): dead drive, stuck cart, or an amplitude inside the bridge's "
                       "deadband or under the breakaway force: record again with a larger --amplitude")
    rms = math.sqrt(cf["sse"])
    lin_rms = rms
    dry_note = ""
    if dry and rms > DRY_COUNTS * count and not fit_db:
        # one duty level: a (|u| - deadband) - Coulomb is one number, the dry cart not identifiable
        dry_note = (" -- a dry cart (Coulomb friction, gear play, deadband) needs cart-only runs at two "
                    "amplitudes or more (--amplitude A and 1.6 A) for its model")
    if dry and rms > DRY_COUNTS * count and fit_db:
        # the linear cart does not explain the log: the dry one (Coulomb friction, gear play,
        # deadband; host.studies.identify_dry), at the linear fit's delay and its neighbours
        dry = _dry_stage(carts, params, d, dmax, cf, oc)
        if dry is not None and dry[1]["sse"] < cf["sse"]:
            d, cf = dry
            sse[d] = cf["sse"]
            rms = math.sqrt(cf["sse"])
    if rms > MAX_RES_COUNTS * count:
        # nothing to identify from a log the drive's model does not fit: say so, in one line
        raise LogError(", ".join(lg.name for lg in carts), "x",
                       f"the cart's drive model does not fit: residual {1e3 * rms:.3f} mm rms, "
                       f"{rms / count:.1f} encoder counts (a clean run fits within {MAX_RES_COUNTS:g}): was the "
                       "cart held, on its end stop, the pendulum still on, or the driver enabled after the disarm? "
                       "record again" + dry_note)
    if cf.get("model") == "dry":
        return _dry_result(carts, params, d, cf, oc, sse, lin_rms, count, max_delay)
    dr = drive_of(cf, params)
    # the whole-tick sensor delay and the latency from the total d + f (module docstring):
    # up to 0.75 of a tick is the board's latency, more is one more tick of delay
    tau = d + cf["f"]
    dw = int(math.floor(tau + 0.25))
    est = {"b": cf["b"], "kt": dr["kt"], "ke": dr["ke"], "delay": dw * dt, "latency": (tau - dw) * dt,
           "deadband": cf["deadband"] / DUTY_MAX}
    ci, _ = _intervals(carts, params, cf, d, est, latency, dbk, oc)
    ci["delay"] = [max(0.0, (dw - 1) * dt), (dw + 1) * dt]
    ci["latency"] = [-0.25 * dt, 0.75 * dt]
    notes = []
    if dry_note:
        notes.append(f"the linear cart fits to {rms / count:.2f} encoder counts rms only{dry_note}")
    free = None
    if one_constant:
        d2, ff, _ = _stage(carts, params, dmax, latency, dbk, db_known, None)
        fd = drive_of(ff, params)
        fe = {"b": ff["b"], "kt": fd["kt"], "ke": fd["ke"], "deadband": ff["deadband"] / DUTY_MAX}
        fci, _ = _intervals(carts, params, ff, d2, fe, latency, dbk, None)
        free = {"kt": fe["kt"], "ke": fe["ke"], "ci": {"kt": fci["kt"], "ke": fci["ke"]},
                "delay_samples": d2 + ff["f"]}
        lo, hi = fci["ke"]
        if math.isfinite(lo) and not lo <= est["kt"] <= hi:
            notes.append(f"kt = ke assumed (one motor constant {est['kt']:.4g}); fitted apart, ke is {fe['ke']:.4g} "
                         f"[{lo:.4g}, {hi:.4g}], kt {fe['kt']:.4g}: check motor.R and motor.V_supply of the robot file")
    if not cf["has_coast"]:
        notes.append("no coast-down in the cart-only runs: b not measured (NaN), ke includes the friction")
    if not fit_db:
        notes.append(f"one duty level: the deadband held at the robot file's {db_known / DUTY_MAX:g} "
                     "(two cart-only runs of different --amplitude fit it)")
    return {"estimates": {k: float(v) for k, v in est.items()}, "ci": ci, "units": CART_UNITS,
            "delay_samples": dw, "latency_samples": tau - dw, "fit_delay": d, "delay_sse": [float(v) for v in sse],
            "fit": cf, "free": free, "one_constant": bool(one_constant), "rows": int(cf["n"]), "model": "linear",
            "logs": [{"file": lg.name, "kind": "cart-only", "rows": len(lg.x)} for lg in carts], "notes": notes}


def _intervals(carts: Sequence[RunLog], params: RobotParams, cf: dict[str, Any], d: int, est: dict[str, float],
               latency: bool, dbk: float | None, oc: tuple[float, float] | None
               ) -> tuple[dict[str, list[float]], dict[str, float]]:
    # 95 % intervals: noise (the Jacobian's covariance, propagated to kt and ke by sampling),
    # the method's bias (each half of the excitation fitted alone at the same delay: a model
    # that does not fit moves with the data it sees) and BIAS_FLOOR, in quadrature
    M, dt = float(params.M), 1.0 / float(params.rate)
    rng = np.random.default_rng(0)
    draws = rng.multivariate_normal([cf["a"], cf["D"], 0.0 if math.isnan(cf["b"]) else cf["b"]], cf["cov"], 400)
    kts, kes = [], []
    for a_, D_, _ in draws:
        dd = drive_of({"a": a_, "D": D_}, params)
        kts.append(dd["kt"])
        kes.append(dd["ke"])
    half = {"kt": 0.5 * (np.percentile(kts, 97.5) - np.percentile(kts, 2.5)),
            "ke": 0.5 * (np.percentile(kes, 97.5) - np.percentile(kes, 2.5)),
            "b": 1.96 * math.sqrt(max(cf["cov"][2, 2], 0.0)) if cf["has_coast"] else math.nan,
            "deadband": 1.96 * math.sqrt(max(cf["cov_full"][4, 4], 0.0)) / DUTY_MAX}
    moves: dict[str, float] = {k: 0.0 for k in ("b", "kt", "ke", "deadband")}
    for part in (0, 1, 2):
        try:
            ph = cart_fit(carts, M, dt, d, latency=latency, deadband=dbk, half=part, one_constant=oc)
        except (ValueError, np.linalg.LinAlgError):
            continue
        pd = drive_of(ph, params)
        pe = {"b": ph["b"], "kt": pd["kt"], "ke": pd["ke"], "deadband": ph["deadband"] / DUTY_MAX}
        for k in moves:
            if math.isfinite(pe[k]) and math.isfinite(est[k]):
                moves[k] = max(moves[k], abs(pe[k] - est[k]))
    ci: dict[str, list[float]] = {}
    for k in ("b", "kt", "ke", "deadband"):
        if not math.isfinite(est[k]) or not math.isfinite(half[k]):
            ci[k] = [math.nan, math.nan]
            continue
        w = math.sqrt(half[k] ** 2 + moves[k] ** 2 + (BIAS_FLOOR[k] * est[k]) ** 2)
        ci[k] = [est[k] - w, est[k] + w]
    return ci, moves


def _dry_stage(carts: Sequence[RunLog], params: RobotParams, d0: int, dmax: int, cf: dict[str, Any],
               oc: tuple[float, float] | None) -> tuple[int, dict[str, Any]] | None:
    # the dry cart at the linear fit's whole delay and its neighbours, started from the linear fit
    from host.studies.identify_dry import dry_fit

    if not all(lg.coast.any() for lg in carts):
        return None  # the Coulomb friction is told from b by the coast-down only
    M, dt = float(params.M), 1.0 / float(params.rate)
    dmin = float(params.values.get("motor.duty_min", 0.0) or 0.0) * DUTY_MAX
    # started from the robot file's drive, not the linear fit's (biased by the dry friction and
    # the play, at times by far)
    v = params.values
    ca, cd = _coefs(params)
    kt = float(v["motor.kt"])
    start = {"a": ca * kt, "D": cd * kt * kt, "b": float(v["cart.b"]), "f": d0 + float(cf["f"]), "brake": 0.5,
             "deadband": float(v.get("motor.deadband", 0.0) or 0.0) * DUTY_MAX}
    ff = dry_fit(carts, M, dt, dmax, start, one_constant=oc, duty_min=dmin)
    return int(ff["d"]), ff


def _dry_result(carts: Sequence[RunLog], params: RobotParams, d: int, cf: dict[str, Any],
                oc: tuple[float, float] | None, sse: list[float], lin_rms: float, count: float,
                max_delay: float) -> dict[str, Any]:
    # identify_cart's result from the dry fit: estimates, 95 % intervals (noise, split halves, floor)
    from host.studies.identify_dry import dry_fit

    M, dt = float(params.M), 1.0 / float(params.rate)
    dmin = float(params.values.get("motor.duty_min", 0.0) or 0.0) * DUTY_MAX
    tau = d + cf["f"]
    dw = int(math.floor(tau + 0.25))

    def est_of(ff: dict[str, Any]) -> dict[str, float]:
        dd = drive_of(ff, params)
        return {"b": ff["b"], "kt": dd["kt"], "ke": dd["ke"], "deadband": ff["deadband"] / DUTY_MAX,
                "coulomb": ff["coulomb"], "backlash": ff["backlash"]}

    est = est_of(cf)
    # noise: the covariance of (a, D, b, coulomb, play, deadband) propagated by sampling
    rng = np.random.default_rng(0)
    idx = [0, 1, 2, 3, 4, 5]
    mean = np.array([cf["a"], cf["D"], cf["b"], cf["coulomb"], cf["backlash"], cf["deadband"]])
    draws = rng.multivariate_normal(mean, cf["cov_full"][np.ix_(idx, idx)], 400, check_valid="ignore")
    samp: dict[str, list[float]] = {k: [] for k in est}
    for a_, D_, b_, fc_, bl_, db_ in draws:
        e_ = est_of({"a": a_, "D": D_, "b": b_, "coulomb": fc_, "backlash": bl_, "deadband": db_})
        for k in est:
            samp[k].append(e_[k])
    half = {k: 0.5 * float(np.percentile(v, 97.5) - np.percentile(v, 2.5)) for k, v in samp.items()}
    moves = {k: 0.0 for k in est}
    start = {k: float(cf[k]) for k in ("a", "D", "b", "brake", "deadband", "coulomb", "hp")}
    start["f"] = float(cf["tau"])
    dmax = int(round(max_delay / dt))
    # the method's bias: each half of the excitation alone, and b (held at the robot file's: not
    # in a dry cart's log) at the ends of the realistic set's friction range (x0.5 .. x2)
    b_file = float(cf["b"])
    for part, bb in ((0, b_file), (1, b_file), (2, b_file), (None, DRY_B_RANGE[0] * b_file),
                     (None, DRY_B_RANGE[1] * b_file)):
        try:
            ph = dry_fit(carts, M, dt, dmax, {**start, "b": bb}, one_constant=oc, duty_min=dmin, half=part)
        except (ValueError, np.linalg.LinAlgError):
            continue
        pe = est_of(ph)
        for k in moves:
            if math.isfinite(pe[k]):
                moves[k] = max(moves[k], abs(pe[k] - est[k]))
    ci: dict[str, list[float]] = {}
    for k in est:
        w = math.sqrt(half[k] ** 2 + moves[k] ** 2 + (DRY_BIAS_FLOOR[k] * est[k]) ** 2
                      + DRY_ABS_FLOOR.get(k, 0.0) ** 2)
        ci[k] = [est[k] - w, est[k] + w]
    for k in ("coulomb", "backlash", "deadband"):
        ci[k][0] = max(0.0, ci[k][0])
    ci["b"] = [DRY_B_RANGE[0] * b_file, DRY_B_RANGE[1] * b_file]  # held, not measured
    # the stiction: not seen by a PRBS that breaks the cart loose at every reversal -- bounded
    # by the Coulomb level below and by the smallest drive force that moved the cart above
    u_min = min(float(np.min(np.abs(lg.duty[~lg.coast][lg.duty[~lg.coast] != 0]))) for lg in carts)
    f_break = cf["a"] * max(u_min - cf["deadband"], 0.0)
    st_file = float(params.values.get("cart.stiction", 0.0) or 0.0)
    est["stiction"] = min(max(st_file, est["coulomb"]), f_break)
    ci["stiction"] = [ci["coulomb"][0], max(f_break, ci["coulomb"][1])]
    est.update(delay=dw * dt, latency=(tau - dw) * dt)
    ci["delay"] = [max(0.0, (dw - 1) * dt), (dw + 1) * dt]
    ci["latency"] = [-0.25 * dt, 0.75 * dt]
    notes = [f"the linear cart did not fit ({lin_rms / count:.1f} encoder counts rms): the dry cart fitted "
             f"({math.sqrt(cf['sse']) / count:.2f} counts) -- Coulomb friction {est['coulomb']:.3g} N, gear play "
             f"{1e3 * est['backlash']:.2f} mm, deadband {100 * est['deadband']:.2f} % of full duty",
             f"b held at the robot file's {b_file:.3g} N s/m (a dry cart's coast-down stops under the Coulomb "
             "friction before b shows), its interval the realistic set's x0.5 .. x2",
             f"the stiction is not resolved by a cart-only PRBS (every reversal breaks the cart loose): "
             f"between the Coulomb level and the drive's {f_break:.3g} N; {est['stiction']:.3g} N written (the dry "
             f"fit's breakaway, where the log shows it: {float(cf.get('stiction', est['coulomb'])):.3g} N)"]
    order = (*CART_NAMES, *DRY_NAMES)
    return {"estimates": {k: float(est[k]) for k in order}, "ci": {k: ci[k] for k in order}, "units": CART_UNITS,
            "delay_samples": dw, "latency_samples": tau - dw, "fit_delay": d, "delay_sse": [float(v) for v in sse],
            "fit": cf, "free": None, "one_constant": oc is not None, "rows": int(cf["n"]), "model": "dry",
            "linear_rms_counts": lin_rms / count,
            "logs": [{"file": lg.name, "kind": "cart-only", "rows": len(lg.x)} for lg in carts], "notes": notes}
