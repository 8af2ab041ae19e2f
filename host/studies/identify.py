"""Identification from the robot's own logs (``upright identify``; issue 15 item 4).

Inputs are logs as ``upright board excite`` records them (the CSV/Parquet format of
:mod:`host.operate.record`, one row per control tick, ``telem_div`` 1): while the firmware's
excitation runs (EXCITE, ``firmware/excite.py``) the ``x`` and ``phi`` columns are the sensors
as read, ``duty`` is the motor duty applied, and the column ``excite`` holds the mode:

- **balancing run** (``excite`` = 1): the robot balances, a PRBS is added to its force;
- **cart-only run** (``excite`` = 2, or the file given with ``--cart-only``): the pendulum
  removed (or locked upright), the PRBS drives the cart open loop; the host then disarms
  while the cart moves and keeps recording: those rows (``duty`` = 0, driver off) are the
  coast-down that separates the cart's friction from the motor's back-EMF.

Known (from ``--params``, the robot TOML: weighed and read off datasheets): the masses
``M`` and ``m``, ``g``, the drive's supply, resistance, gear, wheel radius and motor count,
the sensor scales.  Estimated: the pendulum inertia ``I`` (``J = I + m L^2`` about the pivot),
``m L``, the cart friction ``b``, the motor's force constant ``kt`` (from the duty -> force
gain ``a``) and back-EMF constant ``ke`` (from the drive's speed damping ``D'``), the sensor
delay (whole samples) and the pot offset (counts).  Per candidate delay ``d`` (measurement
``k + d`` is the state at ``k``):

1. cart-only runs, output error (:func:`cart_fit`): ``M xdd = a duty - (D' + b) xd`` driven,
   ``M xdd = -b xd`` coasting, simulated exactly per tick (:func:`cart_sim`) and fitted to the
   positions with ``scipy.optimize.least_squares``: ``a``, ``D'``, ``b``; their covariance from
   the Jacobian (inflated by the residuals' autocorrelation);
2. balancing runs, equation error on signals through one zero-phase Butterworth low-pass
   (linear terms stay exact: filtering commutes with the central differences):
   pendulum ``phidd = (g sin(phi_m) + cos(phi_m) xdd) / Leq - (g beta / Leq) cos(phi_m)`` gives
   ``Leq = J / (m L)`` and the pot offset ``beta`` (rad, the tilt's second derivative is the
   regressand, not a regressor); cart ``(M + m) xdd + b xd - a u + D' xd = kappa cos(phi)
   (g sin(phi) + cos(phi) xdd)`` (the pendulum's reaction ``mL cos(phi) phidd`` through the
   pendulum equation, ``kappa = mL / Leq``; ``mL phid^2 sin(phi)`` is negligible) gives ``mL``.
   In closed loop duty, speed and tilt are nearly collinear: ``a`` and ``D'`` come from step 1
   (without a cart-only run they are fitted here too, poorly conditioned, with a note).

The delay is the ``d`` with the least cart-only residual (else balancing residual).  95 %
intervals: moving-block bootstrap of the balancing rows with ``a, D', b`` drawn from their
covariance, percentiles of every derived parameter; the delay's is the grid's +-1 sample.
They cover noise, not the method's own bias (a few % on ``I`` and ``mL`` in the validation).
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
from scipy import signal

from host.studies.identify_log import LogError, RunLog, read_log
from sim import sensors as ssens
from sim.motor import DUTY_MAX
from sim.params import SCHEMA, RobotParams

__all__ = ["LogError", "RunLog", "read_log", "identify", "robot_toml", "PARAM_NAMES", "truth_of"]

PARAM_NAMES = ("I", "mL", "b", "kt", "ke", "delay", "pot_offset")
"""Estimated parameters: pivot inertia term (kg m^2), m*L (kg m), cart friction (N s/m), force
and back-EMF constants (N m/A, V s/rad), sensor delay (s), pot offset (ADC counts)."""

UNITS = {"I": "kg*m^2", "mL": "kg*m", "b": "N*s/m", "kt": "N*m/A", "ke": "V*s/rad", "delay": "s",
         "pot_offset": "count"}

# ---------------------------------------------------------------- regressions

def _prep(log: RunLog, d: int, sos: np.ndarray, dt: float, edge: int) -> dict[str, np.ndarray]:
    # shift the measurements d samples back (y[k + d] is the state at k), filter, differentiate
    n = len(log.x) - d
    x = log.x[d:d + n]
    ph = log.phi[d:d + n]
    du = log.duty[:n]
    # the force over [k-1, k+1] (what the second difference at k sees): mean of two duties
    u = np.empty(n)
    u[0] = du[0]
    u[1:] = 0.5 * (du[1:] + du[:-1])
    xf = signal.sosfiltfilt(sos, x)
    pf = signal.sosfiltfilt(sos, ph)
    uf = signal.sosfiltfilt(sos, u)
    xd = np.zeros(n)
    xdd = np.zeros(n)
    pd = np.zeros(n)
    pdd = np.zeros(n)
    xd[1:-1] = (xf[2:] - xf[:-2]) / (2 * dt)
    xdd[1:-1] = (xf[2:] - 2 * xf[1:-1] + xf[:-2]) / dt**2
    pd[1:-1] = (pf[2:] - pf[:-2]) / (2 * dt)
    pdd[1:-1] = (pf[2:] - 2 * pf[1:-1] + pf[:-2]) / dt**2
    valid = np.zeros(n, dtype=bool)
    valid[edge:n - edge] = True
    coast = log.coast[:n]
    if log.cart_only and coast.any():
        # the coast-down and the rows the filter mixes with it are not powered rows
        valid[max(0, int(np.argmax(coast)) - edge):] = False
    return {"x": xf, "phi": pf, "u": uf, "xd": xd, "xdd": xdd, "pd": pd, "pdd": pdd, "valid": valid, "coast": coast}


def _rows(log: RunLog, s: dict[str, np.ndarray], M: float, m: float, g: float, beta: float,
          b: float) -> tuple[np.ndarray, ...]:
    # cart equation rows: A @ [a, D', kappa] = y; pendulum rows: P @ [c1, c2] = q
    v = s["valid"]
    n = int(v.sum())
    A = np.zeros((n, 3))
    A[:, 0] = s["u"][v]
    A[:, 1] = -s["xd"][v]
    if log.cart_only:
        y = M * s["xdd"][v] + b * s["xd"][v]
        return A, y, np.zeros((0, 2)), np.zeros(0)
    # the pendulum's reaction through the pendulum equation (mL phidd = kappa w): no second
    # derivative of the (noisier) tilt among the regressors; the phid^2 term is negligible
    ph = s["phi"][v] - beta
    cph, sph = np.cos(ph), np.sin(ph)
    y = (M + m) * s["xdd"][v] + b * s["xd"][v]
    A[:, 2] = cph * (g * sph + cph * s["xdd"][v])
    pm = s["phi"][v]
    cpm = np.cos(pm)
    P = np.column_stack([g * np.sin(pm) + cpm * s["xdd"][v], cpm])
    q = s["pdd"][v]
    return A, y, P, q


def _solve(A: np.ndarray, y: np.ndarray, cols: Sequence[int]) -> np.ndarray:
    th = np.zeros(A.shape[1])
    sol, *_ = np.linalg.lstsq(A[:, cols], y, rcond=None)
    th[list(cols)] = sol
    return th


def _fit(blocks: list[tuple[RunLog, dict[str, np.ndarray]]], M: float, m: float, g: float, b: float,
         drive: tuple[float, float] | None) -> dict[str, Any]:
    # pendulum first (beta, Leq), then the cart with phi corrected by beta
    P = [_rows(lg, s, M, m, g, 0.0, b)[2:] for lg, s in blocks if not lg.cart_only]
    if P:
        Pm = np.vstack([p[0] for p in P])
        qv = np.concatenate([p[1] for p in P])
        c1, c2 = np.linalg.lstsq(Pm, qv, rcond=None)[0]
        Leq, beta = 1.0 / c1, -c2 / (g * c1)
    else:
        Leq, beta = math.nan, 0.0
    bb = 0.0 if math.isnan(b) else b
    B = [_rows(lg, s, M, m, g, beta, bb)[:2] for lg, s in blocks if not lg.cart_only]
    Ab, yb = np.vstack([r[0] for r in B]), np.concatenate([r[1] for r in B])
    if drive is not None:
        # two stages: the drive (a, D') from the open-loop cart (cart_fit), then the
        # pendulum's reaction kappa from the balancing rows (in closed loop duty, speed and
        # tilt are nearly collinear: a free fit of all three there is ill-conditioned)
        th = np.array([drive[0], drive[1], 0.0])
        yk = yb - Ab[:, :2] @ th[:2]
        th[2] = _solve(Ab, yk, [2])[2]
        res = yb - Ab @ th
    else:
        th = _solve(Ab, yb, [0, 1, 2])
        res = yb - Ab @ th
    return {"a": th[0], "D": th[1], "b": b, "mL": th[2] * Leq,
            "Leq": Leq, "beta": beta, "sse": float(res @ res), "n": len(res)}


def _derive(f: dict[str, Any], params: RobotParams, d: int, dt: float) -> dict[str, float]:
    # physical parameters from the regression coefficients and the known constants
    v = params.values
    n, gear, r, R, V = (v["motor.n_motors"], v["motor.gear"], v["motor.r_wheel"], v["motor.R"], v["motor.V_supply"])
    kt = f["a"] * DUTY_MAX * R * r / (n * gear * V)
    ke = f["D"] * R * r**2 / (n * gear**2 * kt) if kt else math.nan
    mL = f["mL"]
    J = f["Leq"] * mL
    I = J - mL**2 / params.m  # noqa: E741 - the model's symbol
    cpr = float(ssens.adc_counts_per_rad(params))
    return {"I": I, "mL": mL, "b": f["b"], "kt": kt, "ke": ke, "delay": d * dt,
            "pot_offset": v["sensors.pot_offset"] + f["beta"] * cpr}


def cart_sim(duty: np.ndarray, driven: np.ndarray, a: float, D: float, b: float, M: float, dt: float) -> np.ndarray:
    """Positions of the cart alone (start at rest, x = 0), exact per tick with the duty held.

    ``M xdd = a duty - (D + b) xd`` on the ``driven`` ticks, ``M xdd = -b xd`` on the others.
    """
    lam = np.where(driven, D + b, b) / M
    lam = np.maximum(lam, 1e-9)
    e = np.exp(-lam * dt)
    vinf = np.where(driven, a * duty, 0.0) / (lam * M)
    n = len(duty)
    v = np.empty(n + 1)
    v[0] = 0.0
    # v[k+1] = vinf[k] + (v[k] - vinf[k]) e[k]: a first-order filter per driven/coast segment
    cuts = [0, *(np.flatnonzero(np.diff(driven.astype(np.int8))) + 1).tolist(), n]
    for i0, i1 in zip(cuts[:-1], cuts[1:]):
        if i1 <= i0:
            continue
        ee = e[i0]
        y, _ = signal.lfilter([1.0 - ee], [1.0, -ee], vinf[i0:i1], zi=[ee * v[i0]])
        v[i0 + 1:i1 + 1] = y
    dx = vinf * dt + (v[:-1] - vinf) * (1.0 - e) / lam
    return np.concatenate([[0.0], np.cumsum(dx)])[:n]


def cart_fit(logs: Sequence[RunLog], M: float, dt: float, d: int) -> dict[str, Any]:
    """Output-error fit of the cart-only runs: ``a``, ``D'``, ``b`` (and one offset per log).

    The measured ``x[k + d]`` against :func:`cart_sim` at ``k``; nonlinear least squares
    (``scipy.optimize.least_squares``), the covariance from its Jacobian.
    """
    from scipy.optimize import least_squares

    data = []
    for lg in logs:
        n = len(lg.x) - d
        data.append((lg.duty[:n], ~lg.coast[:n], lg.x[d:d + n]))
    has_coast = any((~dr).any() for _, dr, _ in data)

    def res(th: np.ndarray) -> np.ndarray:
        a, D = th[0] * 1e-3, th[1] * 10.0
        b = th[2] if has_coast else 0.0
        out = []
        for du, dr, xm in data:
            r = xm - cart_sim(du, dr, a, D, b, M, dt)
            out.append(r - r.mean())
        return np.concatenate(out)

    x0 = np.array([2.0, 4.0, 0.1])
    sol = least_squares(res, x0, bounds=([1e-6, 1e-3, 0.0], [1e3, 1e3, 1e3]), x_scale="jac")
    r = sol.fun
    dof = max(1, len(r) - 3)
    s2 = float(r @ r) / dof
    J = sol.jac
    # neighbouring residuals are correlated (quantisation, model error): the variance
    # inflated by 1 + 2 sum of the residual autocorrelation over 100 lags (clipped at 1)
    rr = r - r.mean()
    den = float(rr @ rr) or 1.0
    rho = [float(rr[:-k] @ rr[k:]) / den for k in range(1, min(100, len(rr) // 4))]
    infl = max(1.0, 1.0 + 2.0 * sum(rho))
    sc = np.array([1e-3, 10.0, 1.0])
    cov = infl * s2 * np.linalg.pinv(J.T @ J) * np.outer(sc, sc)
    th = sol.x * sc
    if not has_coast:
        cov[2, :] = cov[:, 2] = 0.0
    return {"a": th[0], "D": th[1], "b": th[2] if has_coast else math.nan, "cov": cov,
            "sse": float(r @ r) / len(r), "n": len(r)}


def identify(logs: Sequence[RunLog], params: RobotParams, *, fc: float = 10.0, max_delay: float = 0.03,
             n_boot: int = 100, block_s: float = 0.5, seed: int = 0) -> dict[str, Any]:
    """Estimate :data:`PARAM_NAMES` with 95 % confidence intervals from excitation logs.

    Parameters
    ----------
    logs : sequence of RunLog
        At least one balancing run; a cart-only run with a coast-down for ``b`` and ``ke``.
    params : RobotParams
        The known constants (masses, g, drive, sensor scales, loop rate; one row per tick).
    fc : float
        Cut-off (Hz) of the zero-phase low-pass applied to every signal of a balancing run.
    max_delay : float
        Largest sensor delay searched (s), in whole samples.
    n_boot : int
        Bootstrap resamples for the intervals (0: none).
    block_s : float
        Bootstrap block length (s).
    seed : int
        Bootstrap seed.

    Returns
    -------
    dict
        ``estimates`` {name: value}, ``ci`` {name: [lo, hi]}, ``delay_samples``,
        ``delay_sse`` (cart residual per candidate delay), ``rows``, ``logs``, ``notes``.

    Raises
    ------
    ValueError
        No balancing run among the logs.
    """
    if not any(not lg.cart_only for lg in logs):
        raise ValueError("identify needs a balancing run (excite mode 1) among the logs")
    dt = 1.0 / float(params.rate)
    for lg in logs:
        if lg.dt_mean > 2.0 * dt:
            raise LogError(lg.name, "t", f"rows {1e3 * lg.dt_mean:.1f} ms apart, the loop runs at "
                                         f"{params.rate:g} Hz: record every tick (telem_div 1, as upright board "
                                         "excite does) with the loop rate of --params")
    M, m, g = params.M, params.m, params.g
    sos = signal.butter(4, fc, fs=1.0 / dt, output="sos")
    edge = int(math.ceil(3.0 / (fc * dt)))
    dmax = int(round(max_delay / dt))
    carts = [lg for lg in logs if lg.cart_only]
    bals = [lg for lg in logs if not lg.cart_only]
    has_coast = any(lg.coast.any() for lg in carts)
    sse, fits = [], []
    for d in range(dmax + 1):
        cf = cart_fit(carts, M, dt, d) if carts else None
        blocks = [(lg, _prep(lg, d, sos, dt, edge)) for lg in bals]
        f = _fit(blocks, M, m, g, cf["b"] if cf else math.nan, (cf["a"], cf["D"]) if cf else None)
        # the delay from the cart-only fit where there is one (open loop, the sharper test)
        sse.append(cf["sse"] if cf else f["sse"] / f["n"])
        fits.append((f, blocks, cf))
    d = int(np.argmin(sse))
    f, blocks, cf = fits[d]
    if cf:
        f.update(a=cf["a"], D=cf["D"], b=cf["b"])
    est = _derive(f, params, d, dt)
    notes = []
    if not has_coast:
        notes.append("no cart-only run with a coast-down: b not measured (NaN), ke includes the friction")
    if not carts:
        notes.append("no cart-only run: the drive (kt, ke) fitted in closed loop only -- ill-conditioned, "
                     "record a cart-only run (upright board excite --cart-only)")
    # intervals: moving-block bootstrap over the balancing rows (the delay held at its
    # estimate), the drive's (a, D', b) drawn from the cart fit's Jacobian covariance
    ci: dict[str, list[float]] = {}
    if n_boot > 0:
        rng = np.random.default_rng(seed)
        L = max(1, int(round(block_s / dt)))
        draws: dict[str, list[float]] = {k: [] for k in PARAM_NAMES}
        for _ in range(n_boot):
            bb = []
            for lg, s in blocks:
                n = len(s["valid"])
                starts = rng.integers(0, max(1, n - L), max(1, n // L))
                idx = np.concatenate([np.arange(a, min(n, a + L)) for a in starts])
                bb.append((lg, {k: v[idx] for k, v in s.items()}))
            drive, bd = None, math.nan
            if cf:
                a_, D_, b_ = rng.multivariate_normal([cf["a"], cf["D"], 0.0 if math.isnan(cf["b"]) else cf["b"]],
                                                     cf["cov"])
                drive, bd = (a_, D_), (b_ if has_coast else math.nan)
            fb = _fit(bb, M, m, g, bd, drive)
            if cf:
                fb.update(a=drive[0], D=drive[1], b=bd)
            e = _derive(fb, params, d, dt)
            for k in PARAM_NAMES:
                draws[k].append(e[k])
        for k in PARAM_NAMES:
            arr = np.asarray(draws[k], dtype=float)
            arr = arr[np.isfinite(arr)]
            ci[k] = [float(np.percentile(arr, 2.5)), float(np.percentile(arr, 97.5))] if len(arr) else [math.nan] * 2
        ci["delay"] = [max(0.0, (d - 1) * dt), (d + 1) * dt]  # the grid: whole samples
    return {"estimates": {k: float(v) for k, v in est.items()}, "ci": ci, "units": UNITS, "delay_samples": d,
            "delay_sse": [float(v) for v in sse], "rows": int(f["n"]), "fc_hz": fc,
            "logs": [{"file": lg.name, "kind": "cart-only" if lg.cart_only else "balancing", "rows": len(lg.x)}
                     for lg in logs], "notes": notes}


def truth_of(plant: RobotParams) -> dict[str, float]:
    """:data:`PARAM_NAMES` of a (simulated) plant, for validation: ``ke`` = ``kt`` there."""
    return {"I": plant.I, "mL": plant.m * plant.L, "b": plant.b, "kt": plant.kt, "ke": plant.kt,
            "delay": plant.delay, "pot_offset": float(plant.pot_offset)}


def identified_params(result: dict[str, Any], params: RobotParams) -> RobotParams:
    """``params`` with the estimates in place (for ``upright design --params``).

    ``motor.kt`` takes the force constant (the model has one constant for both), the delay is
    rounded to whole control ticks, the pot offset to whole counts; ``pendulum.L_cm`` and
    ``pendulum.I`` are set explicitly (``L_cm = mL / m``).
    """
    e = result["estimates"]
    ch: dict[str, float] = {"pendulum.I": e["I"], "pendulum.L_cm": e["mL"] / params.m, "motor.kt": e["kt"],
                            "sensors.delay": round(e["delay"] * params.rate) / params.rate,
                            "sensors.pot_offset": int(round(e["pot_offset"]))}
    if math.isfinite(e["b"]):
        ch["cart.b"] = max(0.0, e["b"])
    return params.replace(**ch)


def robot_toml(p: RobotParams, note: str = "") -> str:
    """A complete robot TOML of ``p`` (every section; derived keys only where set)."""
    out = [f"# {line}" for line in note.splitlines()] if note else []
    sec = ""
    for key in SCHEMA:
        s, k = key.split(".", 1)
        v = p.values[key]
        if isinstance(v, float) and math.isnan(v):
            continue
        if s != sec:
            out += ["", f"[{s}]"] if out else [f"[{s}]"]
            sec = s
        val = str(int(v)) if SCHEMA[key].integer else repr(float(v))
        k = "I_cm" if key == "pendulum.I" else k  # the file's name of the internal key (sim/robot_file.py)
        out.append(f"{k} = {val}  # {SCHEMA[key].unit}, {SCHEMA[key].doc}")
    return "\n".join(out) + "\n"
