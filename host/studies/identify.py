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
delay (whole samples), the board's read-to-drive latency and the pot offset (counts).  Staged
(issue 24 item 2), never needing a balancing robot for the first stage:

1. **cart-only runs** (:func:`host.studies.identify_cart.identify_cart`, usable alone:
   ``upright identify cart.csv --cart-only``): output error of the positions, each tick
   simulated exactly with the board's timing (the delay in whole ticks plus a fitted latency,
   the enable's delay at the disarm), ``kt = ke`` (one motor constant) by default -- the drive,
   ``b`` from the coast-down, the delay, the latency, the deadband with two amplitudes;
2. **balancing runs**, with the first stage's drive and timing: the pendulum by equation error
   on signals through one zero-phase Butterworth low-pass (linear terms stay exact: filtering
   commutes with the central differences), ``phidd = (g sin(phi_m) + cos(phi_m) xdd) / Leq -
   (g beta / Leq) cos(phi_m)``: ``Leq = J / (m L)`` and the pot offset ``beta`` (rad); ``m L`` by
   output error of the cart's positions (:func:`_reaction_terms`: ``x = X0 + mL X1``, no
   derivative of a measurement) where the logs resolve it -- refitted with the latency
   +-:data:`LAT_SPREAD` tick it must stay within :data:`ML_REL`, and within :data:`ML_AGREE` of the
   robot file's geometry, else the robot file's geometry
   (``pendulum.m_*``, ``L_cm``: weighed and measured) gives ``m L``, said in a note and in
   ``sources``.  With the gear play the first stage found, the balancing run's cart positions
   are first moved from the motor side of the play to the wheel side (:func:`wheel_side`), and
   the difference the move makes to ``I`` is added to its interval as the play model's bias.  On the virtual robot and the bench's plants the cart's back-EMF damping
   (44 N s/m) leaves the pendulum's reaction a fraction of an encoder count (0.03 mm rms):
   ``m L`` comes from the robot file there, ``I`` from ``Leq`` with it.
   Without a cart-only run the drive is fitted in closed loop too, poorly conditioned, with a note.

95 % intervals: the first stage's (noise from the Jacobian, inflated by the residuals'
autocorrelation; the method's bias as the change between the fit and each half of the
excitation fitted alone; :data:`host.studies.identify_cart.BIAS_FLOOR`), in quadrature; for the
balancing stage a moving-block bootstrap of its rows with ``a, D', b`` drawn from the first
stage's covariance, widened by :data:`BIAS_FLOOR` and the latency check.  The delay's is the
grid's +-1 sample.  Logs too short to identify (:data:`MIN_BAL_S`,
:data:`host.studies.identify_cart.MIN_DRIVEN_S`, ``MIN_COAST_S`` board seconds) are refused
in one line saying how many board seconds they need.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, Sequence

import numpy as np
from scipy import signal

from host.studies.identify_cart import DRY_NAMES, _eff, identify_cart
from host.studies.identify_log import LogError, RunLog, read_log
from sim import sensors as ssens
from sim.motor import DUTY_MAX
from sim.params import SCHEMA, RobotParams

__all__ = ["LogError", "RunLog", "read_log", "identify", "identify_cart", "identified_params", "robot_toml",
           "PARAM_NAMES", "STAGE1_EXTRA", "truth_of", "play_fc", "FC_HZ", "wheel_side", "WHEEL_V_HZ", "pot_gain"]

PARAM_NAMES = ("I", "mL", "b", "kt", "ke", "delay", "pot_offset", "pot_gain")
"""Estimated parameters: pivot inertia term (kg m^2), m*L (kg m), cart friction (N s/m), force
and back-EMF constants (N m/A, V s/rad), sensor delay (s), pot offset (ADC counts), the pot's
gain near upright over the robot file's (:func:`pot_gain`; 1 where the logs do not resolve it)."""

STAGE1_EXTRA = ("latency", "deadband")
"""Estimated by the first stage (:func:`identify_cart`) besides :data:`PARAM_NAMES`: the board's
read-to-drive latency (s) and the bridge's deadband (fraction of full duty; held unless fitted)."""

UNITS = {"I": "kg*m^2", "mL": "kg*m", "b": "N*s/m", "kt": "N*m/A", "ke": "V*s/rad", "delay": "s",
         "pot_offset": "count", "pot_gain": "1", "latency": "s", "deadband": "1", "coulomb": "N", "stiction": "N", "backlash": "m"}
BIAS_FLOOR = {"I": 0.05, "mL": 0.04}
"""Fraction of the estimate added (in quadrature) to the bootstrap interval of the balancing stage's
estimates for the method's bias (the equation-error fit through the low-pass)."""
MIN_BAL_S = 5.0
"""Board seconds of balancing excitation a log needs at least."""
FC_HZ = 10.0
"""Hz: the balancing run's low-pass (:func:`identify`'s ``fc``) on a cart without gear play."""
PLAY_XDD = 0.5
"""m/s^2: what the balancing run's low-pass may leave of the encoder's jump across the gear play in
the cart's acceleration (:func:`play_fc`)."""
FC_MIN_HZ = 2.0
"""Hz: the lowest balancing-run low-pass :func:`play_fc` chooses (the pendulum's motion under the
balancing loop lies below it)."""
POT_WIN_S = 1.0
"""s: the windows of :func:`pot_gain`'s integral form (each with its own constant and slope: the
twice-integrated equation's unknown initial position and speed, and its drift)."""
POT_GAIN_MAX = 0.2
"""Largest ``|pot_gain - 1|`` used: beyond it the fit is taken for a failed one (a pot 20 % off its
file's scale near upright is a calibration to repeat, not a nonlinearity), 1 kept, said in a note."""
POT_GAIN_CI = 0.05
"""Largest 95 % half-width of ``pot_gain`` for which the logs' value is used, else 1 (a note).  A short
balancing run on a cart with 3 mm of gear play reads it to 3-4 % (the commission bench's vertices:
0.953 +- 0.035 for a true 0.937): still nearer than 1."""
POT_GAIN_PRIOR = 0.063
"""The half-width of ``pot_gain``'s interval where the logs do not resolve it: the gain error near
upright of a pot with 1 % nonlinearity (``2 pi x 1 %``, ``sim/uncertainty_realistic.toml``'s
``pot_inl`` range; conductive plastic is specified at 0.5-2 %)."""
POT_GAIN_FLOOR = 0.01
"""The method's bias of ``pot_gain`` (added in quadrature to its interval): on the ideal robot
(``tests/test_identify.py``) the windows of 0.5-2 s read 0.9998-1.0057 for a true 1."""


def play_fc(backlash: float, fc: float = FC_HZ) -> float:
    """The balancing run's low-pass (Hz) for a cart with ``backlash`` m of gear play.

    The encoder sits on the motor: each reversal moves it across the play while the cart does not
    follow, a displacement of up to ``backlash`` in the cart's position that the pendulum never
    feels.  Through a low-pass at ``fc`` its second derivative is of the order of ``backlash (2 pi
    fc)^2`` (12 m/s^2 for 3 mm at 10 Hz, against 1-2 m/s^2 of true acceleration): an error in the
    regressor that biases ``Leq`` high, the pivot inertia with it (``J`` +57-87 % at 3 mm and 10 Hz
    on the commission bench's corner robots, +2-8 % at 2 Hz).  The cut-off is lowered until that
    term is :data:`PLAY_XDD`, at least :data:`FC_MIN_HZ`; without play ``fc`` itself.
    """
    if not backlash > 0.0:
        return fc
    return max(FC_MIN_HZ, min(fc, math.sqrt(PLAY_XDD / backlash) / (2.0 * math.pi)))


WHEEL_V_HZ = 5.0
"""Hz: the low-pass of the cart speed :func:`wheel_side` takes from the encoder."""
WHEEL_ITER = 3
"""Passes of :func:`wheel_side`: the cart's speed from the encoder's positions includes the motor's
crossings of the play, each pass takes it from the wheel side the last one found."""


def wheel_side(lg: RunLog, d: int, a: float, D: float, deadband: float, backlash: float, dt: float) -> RunLog:
    """A balancing log with ``x`` moved from the motor side of the gear play to the wheel side.

    The encoder sits on the motor: at each reversal it crosses the play while the cart does not
    follow, and the pendulum's equation (:func:`_rows`) sees the jump as the cart's acceleration.
    The play's state is reconstructed as the simulators and the firmware's gap model have it (the
    massless motor free in the play at its no-load speed ``v0 = a u_eff / D'``, against the cart's
    speed -- the wheel side's through a :data:`WHEEL_V_HZ` low-pass, :data:`WHEEL_ITER` passes
    from the encoder's -- clamped to half the play), on the duty's timeline, and subtracted from
    each row ``d`` ticks later (the measurement's delay).  A commission-bench robot with 2.9 mm of
    play and 0.46 N of Coulomb friction: the pivot inertia -10 % off without it, its interval
    missing the truth; +1.8 % with it (+0.6 % with the play and friction alone, -0.7 % with no
    realism at all).  A 3 mm corner with the pot's nonlinearity at +1 % (its gain near upright
    +6 %) stays +17-18 % off: that bias is the pot's, not the play's.

    Parameters
    ----------
    lg : RunLog
        A balancing run.
    d : int
        The sensor delay (whole ticks) of the first stage.
    a, D, deadband : float
        The first stage's duty gain (N per count), back-EMF damping (N s/m), deadband (counts).
    backlash : float
        The first stage's gear play (m, total).
    dt : float
        Control period (s).

    Returns
    -------
    RunLog
        A copy of ``lg`` with ``x`` on the wheel side (``lg`` itself without play).
    """
    import copy

    if not (backlash > 0.0 and D > 0.0):
        return lg
    x = np.asarray(lg.x, dtype=float)
    n = len(x)
    v0 = a * _eff(np.asarray(lg.duty, dtype=float), deadband) / D
    sos = signal.butter(2, WHEEL_V_HZ, fs=1.0 / dt, output="sos")
    hp = 0.5 * backlash
    xw = x.copy()
    for _ in range(WHEEL_ITER):
        # the cart's speed from the wheel side found so far, on the duty's timeline (the row d
        # ticks later measured it), then the play's state again
        vm = np.gradient(signal.sosfiltfilt(sos, xw), dt)
        vc = np.empty(n)
        vc[:n - d] = vm[d:]
        vc[n - d:] = vm[-1]
        delta = np.zeros(n)
        q = 0.0
        for k in range(1, n):
            q += dt * (v0[k - 1] - vc[k - 1])
            q = hp if q > hp else (-hp if q < -hp else q)
            delta[k] = q
        xw = x.copy()
        xw[d:] -= delta[:n - d]
    out = copy.copy(lg)
    out.x = xw
    return out


def _pot_rows(x: np.ndarray, ph: np.ndarray, valid: np.ndarray, dt: float, win: int) -> tuple[np.ndarray, np.ndarray]:
    # per window of `win` valid rows: the columns (phi, its double integral, t^2) and the target x,
    # each with the window's own line (constant and slope) projected out
    idx = np.flatnonzero(valid)
    R, Y = [], []
    for w in range(len(idx) // win):
        sl = idx[w * win:(w + 1) * win]
        if sl[-1] - sl[0] != win - 1:
            continue  # not contiguous
        p = ph[sl]
        t = np.arange(win) * dt
        s1 = np.concatenate([[0.0], np.cumsum(0.5 * (p[1:] + p[:-1])) * dt])
        s2 = np.concatenate([[0.0], np.cumsum(0.5 * (s1[1:] + s1[:-1])) * dt])
        C = np.column_stack([p, s2, t * t])
        L = np.column_stack([np.ones(win), t])
        q, _ = np.linalg.qr(L)
        R.append(C - q @ (q.T @ C))
        y = x[sl]
        Y.append(y - q @ (q.T @ y))
    return np.stack(R) if R else np.zeros((0, win, 3)), np.stack(Y) if Y else np.zeros((0, win))


def pot_gain(blocks: Sequence[tuple[RunLog, dict[str, np.ndarray]]], g: float, dt: float, *, n_boot: int = 200,
             seed: int = 0) -> tuple[float, float]:
    """The pot's gain near upright over the robot file's, from the balancing runs: ``(k, 95 % half-width)``.

    The pendulum's equation ``Leq phidd = g phi + xdd`` (linearised; ``Leq = J / (m L)``) integrated
    twice over a window: ``Leq phi - x = g SS phi + c0 + c1 t``.  A reading ``phi_m = k phi + beta``
    (the pot's local gain ``k``: its nonlinearity, a calibration tilt read as a secant) makes it
    ``x = (Leq / k) phi_m - (g / k) SS phi_m + (g beta / 2 k) t^2 + c0' + c1' t``: the known ``g``
    separates the gain from ``Leq``, which the differential form's single coefficient
    (``(g phi_m + k xdd) / Leq``) cannot -- a pot reading 6 % high near upright (``pot_inl`` 1 %)
    made the pivot inertia 12 % high.  No derivative of a measurement, and both sensors carry the
    same delay (none to shift).  ``blocks``: the balancing runs with their filtered signals
    (``_prep``'s ``x``, ``phi``, ``valid``); windows of :data:`POT_WIN_S`; the interval from a
    bootstrap over the windows.
    """
    win = max(8, int(round(POT_WIN_S / dt)))
    parts = [_pot_rows(s["x"], s["phi"], s["valid"], dt, win) for lg, s in blocks if not lg.cart_only]
    R = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, win, 3))
    Y = np.concatenate([p[1] for p in parts]) if parts else np.zeros((0, win))
    if len(R) < 3:
        return math.nan, math.inf

    def solve(ix: np.ndarray) -> float:
        A = R[ix].reshape(-1, 3)
        th = np.linalg.lstsq(A, Y[ix].reshape(-1), rcond=None)[0]
        return -g / th[1] if th[1] < 0 else math.nan

    k = solve(np.arange(len(R)))
    rng = np.random.default_rng(seed)
    ks = np.array([solve(rng.integers(0, len(R), len(R))) for _ in range(n_boot)])
    ks = ks[np.isfinite(ks)]
    if not math.isfinite(k) or len(ks) < n_boot // 2:
        return math.nan, math.inf
    lo, hi = np.percentile(ks, [2.5, 97.5])
    return float(k), float(max(hi - k, k - lo))


def check_balancing_log(lg: RunLog, rate: float, fc: float) -> None:
    """Refuse (one line, :class:`LogError`) a balancing log too short to identify the pendulum."""
    if len(lg.x) < MIN_BAL_S * rate:
        raise LogError(lg.name, "", f"{len(lg.x) / rate:.2f} s of board time excited, the pendulum's fit needs at "
                                    f"least {MIN_BAL_S:g} s: record again with `upright board excite "
                                    f"--board-seconds {2 * MIN_BAL_S:g}`")

# ---------------------------------------------------------------- regressions

def _prep(log: RunLog, d: int, sos: np.ndarray, dt: float, edge: int, f: float = 0.0,
          deadband: float = 0.0) -> dict[str, np.ndarray]:
    # shift the measurements d samples back (y[k + d] is the state at k), filter, differentiate
    n = len(log.x) - d
    x = log.x[d:d + n]
    ph = log.phi[d:d + n]
    du = _eff(log.duty[:n], deadband)
    # the duty over tick k: the previous one for the latency f, then its own (identify_cart)
    ui = du.copy()
    ui[1:] = (1.0 - f) * du[1:] + f * du[:-1]
    # the force over [k-1, k+1] (what the second difference at k sees): mean of two ticks
    u = np.empty(n)
    u[0] = ui[0]
    u[1:] = 0.5 * (ui[1:] + ui[:-1])
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
    return {"x": xf, "phi": pf, "u": uf, "xd": xd, "xdd": xdd, "pd": pd, "pdd": pdd, "valid": valid, "coast": coast,
            "x_raw": x, "phi_raw": ph, "duty_raw": log.duty[:n]}


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


LAT_SPREAD = 0.25
"""Ticks by which a balancing tick's read-to-drive latency may differ from the cart-only run's."""
ML_REL = 0.10
"""Largest 95 % half-width of m*L (fraction) for which the logs' value is used, else the robot file's."""
ML_AGREE = 0.25
"""Largest difference (fraction) between the logs' m*L and the robot file's geometry (``m L_cm``:
weighed, the centre of mass found by balancing the pendulum) for which the logs' value is used.
The reaction fit can pass its own latency check and still be far off: at the corner robot of
``tests/test_commission.py`` (inertia x0.5, masses x1.2, kt x0.9) it read 0.1095 kg m for a true
0.0629 on one machine and not on another (the cart's positions move by a fraction of an encoder
count; a last-bit difference in the plant's arithmetic moves a count), and the pivot inertia
``J - (m L)^2 / m`` then came out negative."""
HP_HZ = 0.5
"""High-pass (Hz) of the balancing run's cart positions in the reaction fit: the open-loop
integration of the drive model drifts, the pendulum's reaction is faster."""


def _reaction_terms(s: dict[str, np.ndarray], drive: dict[str, float], M: float, m: float, dt: float,
                    beta: float) -> tuple[np.ndarray, np.ndarray]:
    """The balancing run's cart positions by output error: target ``HP(x - X0)`` and regressor ``HP(X1)``.

    ``(M + m) xdd = a u_eff - (D' + b) xd + mL d^2(sin phi)/dt^2`` (sim.plant): with
    ``lam = (D' + b) / (M + m)`` its solution is ``x = X0 + mL X1``, ``X0`` the drive's response
    to the duty (:func:`host.studies.identify_cart.cart_sim`, mass ``M + m``, the cart-only
    stage's timing) and ``X1 = (sin phi - LP_lam(sin phi)) / (M + m)`` -- no derivative of a
    measurement.  Both through one zero-phase high-pass (:data:`HP_HZ`).
    """
    from host.studies.identify_cart import cart_sim

    du = s["duty_raw"]
    X0 = cart_sim(du, np.ones(len(du), dtype=bool), drive["a"], drive["D"], drive["b"], M + m, dt,
                  f=drive["f"], deadband=drive["deadband"])
    sn = np.sin(s["phi_raw"] - beta)
    lam = (drive["D"] + drive["b"]) / (M + m)
    e = math.exp(-lam * dt)
    src = np.empty_like(sn)
    src[0] = sn[0]
    src[1:] = 0.5 * (sn[1:] + sn[:-1])  # the tilt over each tick (its mean)
    lp, _ = signal.lfilter([1.0 - e], [1.0, -e], src, zi=[e * sn[0]])
    X1 = (sn - lp) / (M + m)
    hp = signal.butter(2, HP_HZ, btype="highpass", fs=1.0 / dt, output="sos")
    return signal.sosfiltfilt(hp, s["x_raw"] - X0), signal.sosfiltfilt(hp, X1)


def _solve(A: np.ndarray, y: np.ndarray, cols: Sequence[int]) -> np.ndarray:
    th = np.zeros(A.shape[1])
    sol, *_ = np.linalg.lstsq(A[:, cols], y, rcond=None)
    th[list(cols)] = sol
    return th


def _fit(blocks: list[tuple[RunLog, dict[str, np.ndarray]]], M: float, m: float, g: float, b: float,
         drive: tuple[float, float] | None, full: dict[str, float] | None = None, dt: float = 0.0) -> dict[str, Any]:
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
    if full is not None:
        # two stages: the drive from the open-loop cart (identify_cart), then m*L from the
        # balancing run's positions by output error (_reaction_terms; the equation error of
        # the cart's force balance subtracts two large, nearly equal terms, a u and D' xd,
        # and is at the mercy of the drive's timing)
        num = den = 0.0
        n_ = 0
        for lg, s_ in blocks:
            v = s_["valid"]
            y_, x1 = (s_["react_y"], s_["react_x"]) if "react_y" in s_ else _reaction_terms(s_, full, M, m, dt, beta)
            num += float(y_[v] @ x1[v])
            den += float(x1[v] @ x1[v])
            n_ += int(v.sum())
        mL = num / den if den > 0 else math.nan
        th = np.array([drive[0], drive[1], mL / Leq])
        res = yb - Ab @ th
    else:
        th = _solve(Ab, yb, [0, 1, 2])
        res = yb - Ab @ th
    return {"a": th[0], "D": th[1], "b": b, "mL": th[2] * Leq,
            "Leq": Leq, "beta": beta, "sse": float(res @ res), "n": len(res)}


def _derive(f: dict[str, Any], params: RobotParams, d: int, dt: float,
            mL_known: float | None = None, pot_k: float = 1.0) -> dict[str, float]:
    # physical parameters from the regression coefficients and the known constants
    v = params.values
    n, gear, r, R, V = (v["motor.n_motors"], v["motor.gear"], v["motor.r_wheel"], v["motor.R"], v["motor.V_supply"])
    kt = f["a"] * DUTY_MAX * R * r / (n * gear * V)
    ke = f["D"] * R * r**2 / (n * gear**2 * kt) if kt else math.nan
    mL = f["mL"] if mL_known is None else mL_known
    J = f["Leq"] * mL
    I = J - mL**2 / params.m  # noqa: E741 - the model's symbol
    cpr = float(ssens.adc_counts_per_rad(params))
    return {"I": I, "mL": mL, "b": f["b"], "kt": kt, "ke": ke, "delay": d * dt,
            "pot_offset": v["sensors.pot_offset"] + f["beta"] * cpr * pot_k, "pot_gain": pot_k}


def identify(logs: Sequence[RunLog], params: RobotParams, *, fc: float | None = None, max_delay: float = 0.03,
             n_boot: int = 100, block_s: float = 0.5, seed: int = 0) -> dict[str, Any]:
    """Estimate :data:`PARAM_NAMES` with 95 % confidence intervals from excitation logs.

    Parameters
    ----------
    logs : sequence of RunLog
        At least one balancing run; a cart-only run with a coast-down for ``b`` and ``ke``.
    params : RobotParams
        The known constants (masses, g, drive, sensor scales, loop rate; one row per tick).
    fc : float, optional
        Cut-off (Hz) of the zero-phase low-pass applied to every signal of a balancing run;
        default :data:`FC_HZ`, lowered for the gear play the cart-only stage found (:func:`play_fc`).
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
    dmax = int(round(max_delay / dt))
    carts = [lg for lg in logs if lg.cart_only]
    bals = [lg for lg in logs if not lg.cart_only]
    for lg in bals:
        check_balancing_log(lg, params.rate, fc or FC_HZ)
    has_coast = any(lg.coast.any() for lg in carts)
    bals_motor: list[RunLog] | None = None  # the balancing runs as read, where the wheel side moved them
    # the first stage (identify_cart): the drive, the friction, the delay and the latency, open
    # loop; the balancing rows then see the same timing and deadband (and its gear play, the
    # low-pass: play_fc)
    cres = identify_cart(carts, params, max_delay=max_delay) if carts else None
    if fc is None:
        fc = play_fc(float(cres["estimates"].get("backlash", 0.0)) if cres is not None else 0.0)
    sos = signal.butter(4, fc, fs=1.0 / dt, output="sos")
    edge = int(math.ceil(3.0 / (fc * dt)))
    fl, db = 0.0, 0.0
    if cres is not None:
        cf = cres["fit"]
        d, fl, db = int(cres["fit_delay"]), float(cf["f"]), float(cf["deadband"])
        sse = list(cres["delay_sse"])
        # the gear play the cart-only runs found: the balancing rows' cart on the wheel side
        play = float(cres["estimates"].get("backlash", 0.0))
        if play > 0.0:
            bals_motor = bals
            bals = [wheel_side(lg, d, float(cf["a"]), float(cf["D"]), db, play, dt) for lg in bals]
    # the pot's gain near upright (pot_gain): the balancing runs' tilt rescaled to it, so that Leq,
    # the offset and the reaction's m*L are all in true radians
    kp, kh = pot_gain([(lg, _prep(lg, 0, sos, dt, edge)) for lg in bals], g, dt, seed=seed)
    kp_fit = kp
    pot_ok = math.isfinite(kp) and abs(kp - 1.0) <= POT_GAIN_MAX and kh <= POT_GAIN_CI
    pot_used = pot_ok and abs(kp - 1.0) > kh
    if pot_used:
        bals = [replace(lg, phi=lg.phi / kp) for lg in bals]
        if bals_motor is not None:
            bals_motor = [replace(lg, phi=lg.phi / kp) for lg in bals_motor]
    else:
        kp = 1.0
    if cres is not None:
        blocks = [(lg, _prep(lg, d, sos, dt, edge, fl, db)) for lg in bals]
        full = {k: float(cf[k]) for k in ("a", "D", "b", "f", "deadband")}
        f = _fit(blocks, M, m, g, cf["b"], (cf["a"], cf["D"]), full, dt)
        f.update(a=cf["a"], D=cf["D"], b=cf["b"])
    else:
        cf = None
        sse, fits = [], []
        for dd in range(dmax + 1):
            blocks = [(lg, _prep(lg, dd, sos, dt, edge)) for lg in bals]
            ff = _fit(blocks, M, m, g, math.nan, None)
            sse.append(ff["sse"] / ff["n"])
            fits.append((ff, blocks))
        d = int(np.argmin(sse))
        f, blocks = fits[d]
    est = _derive(f, params, d, dt, pot_k=kp)
    if cres is not None:
        ce = cres["estimates"]
        est.update(kt=ce["kt"], ke=ce["ke"], b=ce["b"], delay=ce["delay"])
        est["latency"] = ce["latency"]
        est["deadband"] = ce["deadband"]
        # the dry cart's (identify_cart fitted it: the linear cart did not fit the cart-only runs);
        # the balancing stage below still models the cart's reaction as linear
        est.update({k: ce[k] for k in DRY_NAMES if k in ce})
    notes = list(cres["notes"]) if cres is not None else []
    if pot_used:
        notes.append(f"pot gain near upright {kp:.4f} x the robot file's (95 % +-{kh:.3f}, from the pendulum's "
                     f"equation integrated twice, pot_gain): the balancing runs' tilt rescaled; the identified robot's "
                     f"pot_range is the file's / {kp:.4f}")
    elif pot_ok:
        notes.append(f"pot gain near upright {kp_fit:.4f} (95 % +-{kh:.3f}): 1 within its interval, the robot file's "
                     "scale kept (pot_gain 1)")
    else:
        notes.append("pot gain near upright not resolved by the logs (" + (
            f"{kp_fit:.4f} +-{kh:.3f}" if math.isfinite(kp_fit) else "no fit") + f", used within "
            f"+-{POT_GAIN_CI:g} and {POT_GAIN_MAX:g} of 1): the robot file's scale kept (pot_gain 1)")
    sources = {k: "logs" for k in PARAM_NAMES}
    if carts and not has_coast:
        pass  # said by identify_cart
    if not carts:
        notes.append("no cart-only run: the drive (kt, ke) fitted in closed loop only -- ill-conditioned, "
                     "record a cart-only run (upright board excite --cart-only)")
        notes.append("no cart-only run with a coast-down: b not measured (NaN), ke includes the friction")
    mLk: float | None = None
    mv = 0.0
    if cf is not None:
        # the method's bias in m*L: the read-to-drive latency of a balancing tick is not the
        # cart-only run's (a longer computation), and m*L follows it closely -- refitted at
        # +-LAT_SPREAD ticks; beyond ML_REL (or not positive) the logs do not resolve m*L
        # (_reaction_terms: the cart's strong back-EMF damping leaves the pendulum's reaction
        # a fraction of an encoder count) and the robot file's geometry gives it (the
        # pendulum's masses and centre of mass: weighed and measured); the pivot inertia then
        # comes from the pendulum's Leq = J / (m L) alone
        for df in (-LAT_SPREAD, LAT_SPREAD):
            fl2 = max(0.0, fl + df)
            bl2 = [(lg, _prep(lg, d, sos, dt, edge, fl2, db)) for lg in bals]
            f2 = _fit(bl2, M, m, g, cf["b"], (cf["a"], cf["D"]), dict(full, f=fl2), dt)
            mv = max(mv, abs(f2["mL"] - f["mL"]))
        geo = float(params.m * params.L)
        resolved = math.isfinite(est["mL"]) and est["mL"] > 0 and mv <= ML_REL * est["mL"]
        if not (resolved and abs(est["mL"] - geo) <= ML_AGREE * geo):
            mLk = geo
            why = (f"the logs do not resolve it (from the cart's positions {est['mL']:.3g} kg m, +-{mv:.2g} with the "
                   f"latency +-{LAT_SPREAD:g} tick)" if not resolved else
                   f"the logs' {est['mL']:.3g} kg m (+-{mv:.2g} with the latency +-{LAT_SPREAD:g} tick) is more than "
                   f"{100 * ML_AGREE:.0f} % from it: check the weighing, else the logs' fit is off")
            notes.append(f"m*L from --params ({mLk:.4g} kg m: the pendulum's masses and centre of mass), {why}; "
                         "I from the pendulum's Leq with it")
            sources["mL"] = "params"
            est.update({k: v for k, v in _derive(f, params, d, dt, mLk, pot_k=kp).items() if k in ("I", "mL")})
    # the method's bias from the gear play: the play's state is a model's (wheel_side), so the
    # pendulum fitted on the motor side's positions bounds how far that model moves I
    model_bias: dict[str, float] = {}
    if bals_motor is not None:
        bm = [(lg, _prep(lg, d, sos, dt, edge, fl, db)) for lg in bals_motor]
        fm = _fit(bm, M, m, g, cf["b"], (cf["a"], cf["D"]), full, dt)
        em = _derive(fm, params, d, dt, mLk, pot_k=kp)
        if math.isfinite(em["I"]) and math.isfinite(est["I"]):
            model_bias["I"] = abs(em["I"] - est["I"])
            notes.append(f"gear play {1e3 * play:.2f} mm: the balancing run's cart "
                         f"moved to the wheel side of the play (wheel_side); on the motor side I would read "
                         f"{em['I']:.4g}, a difference added to its interval as the play model's bias")
    # the method's bias from the pot's gain: the pendulum refitted with the gain at the far end of
    # its interval (the rows below are bootstrapped with it held)
    kw = math.hypot(kh, POT_GAIN_FLOOR * kp) if pot_ok else POT_GAIN_PRIOR
    if cf is not None and math.isfinite(est["I"]):
        k2 = kp + kw
        bk = [(lg, _prep(replace(lg, phi=lg.phi * kp / k2), d, sos, dt, edge, fl, db)) for lg in bals]
        ek = _derive(_fit(bk, M, m, g, cf["b"], (cf["a"], cf["D"]), full, dt), params, d, dt, mLk, pot_k=k2)
        if math.isfinite(ek["I"]):
            model_bias["I"] = math.hypot(model_bias.get("I", 0.0), ek["I"] - est["I"])
    # intervals: moving-block bootstrap over the balancing rows (the delay held at its
    # estimate), the drive's (a, D', b) drawn from the cart fit's Jacobian covariance
    ci: dict[str, list[float]] = {}
    if n_boot > 0:
        rng = np.random.default_rng(seed)
        L = max(1, int(round(block_s / dt)))
        draws: dict[str, list[float]] = {k: [] for k in PARAM_NAMES}
        boots: list[dict[str, Any]] = []
        for _ in range(n_boot):
            drive, bd, fd = None, math.nan, None
            if cf:
                a_, D_, b_ = rng.multivariate_normal([cf["a"], cf["D"], 0.0 if math.isnan(cf["b"]) else cf["b"]],
                                                     cf["cov"])
                drive, bd = (a_, D_), (b_ if has_coast else math.nan)
                fd = dict(full, a=a_, D=D_, b=b_ if has_coast else 0.0)
            bb = []
            for lg, s in blocks:
                n = len(s["valid"])
                starts = rng.integers(0, max(1, n - L), max(1, n // L))
                idx = np.concatenate([np.arange(a, min(n, a + L)) for a in starts])
                s2 = dict(s)
                if fd is not None:
                    # the reaction terms on the whole run (a time series), then resampled
                    s2["react_y"], s2["react_x"] = _reaction_terms(s, fd, M, m, dt, f["beta"])
                bb.append((lg, {k: v[idx] for k, v in s2.items()}))
            fb = _fit(bb, M, m, g, bd, drive, fd, dt)
            if cf:
                fb.update(a=drive[0], D=drive[1], b=bd)
            boots.append(fb)
            e = _derive(fb, params, d, dt, pot_k=kp)
            for k in PARAM_NAMES:
                draws[k].append(e[k])
        if mLk is not None:
            draws["I"] = [_derive(fb, params, d, dt, mLk, pot_k=kp)["I"] for fb in boots]
            draws["mL"] = [mLk]
        elif mv > 0:
            draws["mL"] = list(draws["mL"]) + [est["mL"] - mv, est["mL"] + mv]
        for k in PARAM_NAMES:
            arr = np.asarray(draws[k], dtype=float)
            arr = arr[np.isfinite(arr)]
            ci[k] = [float(np.percentile(arr, 2.5)), float(np.percentile(arr, 97.5))] if len(arr) else [math.nan] * 2
            if k in BIAS_FLOOR and len(arr) and math.isfinite(est[k]):
                # the method's bias (measured in the validation) on top of the noise, in quadrature
                lo, hi = ci[k]
                w = math.hypot(BIAS_FLOOR[k] * abs(est[k]), model_bias.get(k, 0.0))  # the play model's and the pot gain's
                ci[k] = [est[k] - math.hypot(est[k] - lo, w), est[k] + math.hypot(hi - est[k], w)]
        ci["delay"] = [max(0.0, (d - 1) * dt), (d + 1) * dt]  # the grid: whole samples
        # the pot's gain: its own bootstrap over the windows (the pendulum's rows are fitted with it
        # held), the method's floor in quadrature; unresolved, a pot's usual gain error (POT_GAIN_PRIOR)
        ci["pot_gain"] = [kp - kw, kp + kw]
    if cres is not None:
        # the first stage's intervals (noise, split-half bias and its floor) for what it estimates
        for k in ("b", "kt", "ke", "delay", "latency", "deadband", *(x for x in DRY_NAMES if x in cres["ci"])):
            ci[k] = list(cres["ci"][k])
        d = int(cres["delay_samples"])
    return {"estimates": {k: float(v) for k, v in est.items()}, "ci": ci, "units": UNITS, "delay_samples": d,
            "delay_sse": [float(v) for v in sse], "rows": int(f["n"]), "fc_hz": fc, "sources": sources,
            "logs": [{"file": lg.name, "kind": "cart-only" if lg.cart_only else "balancing", "rows": len(lg.x)}
                     for lg in logs], "notes": notes}


def truth_of(plant: RobotParams) -> dict[str, float]:
    """:data:`PARAM_NAMES` of a (simulated) plant, for validation: ``ke`` = ``kt`` there."""
    return {"I": plant.I, "mL": plant.m * plant.L, "b": plant.b, "kt": plant.kt, "ke": plant.kt,
            "delay": plant.delay, "pot_offset": float(plant.pot_offset),
            "pot_gain": float(ssens.pot_gain_at_upright(plant))}


def identified_params(result: dict[str, Any], params: RobotParams) -> RobotParams:
    """``params`` with the estimates in place (for ``upright design --params``).

    ``motor.kt`` takes the force constant (the model has one constant for both), the delay is
    rounded to whole control ticks, the pot offset to whole counts; ``pendulum.L_cm`` and
    ``pendulum.I`` are set explicitly (``L_cm = mL / m``), the pot's gain near upright
    (``pot_gain``) scales its counts per radian (``sensors.pot_range`` / ``pot_gain``: the
    tables' tilt is then true radians where the robot balances).  A first-stage result
    (:func:`identify_cart`: no ``I``, ``mL``, pot offset) sets only the drive, the friction and
    the delay; a deadband fitted (two amplitudes) goes to ``motor.deadband``; the dry cart's
    Coulomb friction, stiction and gear play (``identify_cart(..., dry=True)``) to
    ``cart.coulomb``, ``cart.stiction`` and ``motor.backlash``.
    """
    e = result["estimates"]
    ch: dict[str, float] = {}
    if "I" in e and "mL" in e:
        ch.update({"pendulum.I": e["I"], "pendulum.L_cm": e["mL"] / params.m})
    if "pot_offset" in e:
        ch["sensors.pot_offset"] = int(round(e["pot_offset"]))
    if math.isfinite(e.get("pot_gain", math.nan)) and e["pot_gain"] > 0 and e["pot_gain"] != 1.0:
        ch["sensors.pot_range"] = params.pot_range / e["pot_gain"]
    if math.isfinite(e.get("kt", math.nan)):
        ch["motor.kt"] = e["kt"]
    if "delay" in e:
        ch["sensors.delay"] = round(e["delay"] * params.rate) / params.rate
    if math.isfinite(e.get("b", math.nan)):
        ch["cart.b"] = max(0.0, e["b"])
    if not any("deadband held" in n for n in result.get("notes", ())) and math.isfinite(e.get("deadband", math.nan)) \
            and "motor.deadband" in params.values:
        ch["motor.deadband"] = max(0.0, e["deadband"])
    # the dry cart's (identify_cart(dry=True)): Coulomb friction, breakaway, gear play
    for k, key in (("coulomb", "cart.coulomb"), ("stiction", "cart.stiction"), ("backlash", "motor.backlash")):
        if math.isfinite(e.get(k, math.nan)):
            ch[key] = max(0.0, e[k])
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
