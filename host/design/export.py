"""Fixed-point export: the discrete controller as integer tables for the firmware.

The firmware (``firmware/controller.py``) runs the structured form of
:class:`host.design.discrete.DiscreteController` in integers.  Every quantity has a fixed
binary scale (one LSB in SI units):

=========  =======================================  ==============================
quantity   LSB                                      limit (clamp, saturating)
=========  =======================================  ==============================
x          encoder count / 2**QX                    2 * track
xdot       2**-EV m/s                               V_LIMIT (16 m/s)
phi        ADC count / 2**QP                        pi/2
phidot     2**-EW rad/s                             W_LIMIT (120 rad/s)
u (force)  2**-EU N                                 u_max (stall force)
=========  =======================================  ==============================

Each tick (``y`` = clamped measurements, ``r`` = reference, ``b`` = stored saturated
forces, ``>>`` an arithmetic shift with rounding ``(acc + 2**(S-1)) >> S``)::

    e      = y - C p                                   (innovation, |e| <= 2 * limit)
    xf_i   = clamp(p_i + (M_i . e + rf_i) >> SM_i)
    u      = clamp((KF . xf + KB . b + KR r + KI integ) >> SK, +-ULIM)
    vh     = clamp((KV . xf + KVB . b) >> SKV)         (predicted current cart speed)
    p_i    = clamp(xf_i + (AD_i . xf + BD_i b_0 + ra_i) >> SA_i)   (AD = Ad - I: delta form)

The recursive rows (filter, update) use error feedback instead of rounding: the
remainder ``rf_i``/``ra_i`` (``0 <= r < 2**S``) of each shift is carried into the next
tick, so corrections smaller than one LSB accumulate instead of being lost (without it
the estimator has a rounding dead zone: a cart speed below ~0.01 m/s never moved x).
    duty   = clamp((KDU u + KDV vh) >> SD + deadband, +-32767)

**Headroom proof.**  Every accumulator is a sum ``sum_j G_j in_j + 2**(S-1)`` whose inputs
are clamped to declared bounds ``|in_j| <= B_j`` *before* they enter it (states and
forces are clamped when stored, measurements when converted, the reference when set),
so every partial sum, in any order, is bounded by ``sum_j |G_j| B_j + 2**(S-1)``.  The
shift of each row is the largest for which that bound is ``<= 2**30 - 1``; the bounds
are written into the generated module's header and re-checked by
``tests/test_export_headroom.py`` and, for uploaded tables, by the firmware itself.

The tables are flattened in :data:`LAYOUT` order into one int list (little-endian int32
on the wire, CRC-16/CCITT-FALSE over those bytes) so a gain upload can be validated:
header ``[VERSION, D, LEN]`` fixes the version and shape.

**Estimator per table** (``EST``): 0 is the full estimator above (the Kalman gain in ``M``), 1
the reduced-order observer of :mod:`host.design.reduced` in the same predictor-corrector form
(:func:`filter_gain`): its ``M`` rows of x and phi are the identity, so the firmware takes the
measured states straight from the sensors and skips those two filter rows, and the rows of
xdot and phidot hold ``Lr``.  The prediction ``p`` keeps every stored number inside the
state's own range; the Gopinath state ``z = w - Lr y`` would need ``|w| + |Lr| |y|`` (about
80 m/s for the cart at a 40 rad/s observer on a 2 m track), a coarser LSB for the same bits.
"""

from __future__ import annotations

import math
import struct
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from host.design.catch import CATCH_DEFAULT, CatchDesign, catch_clamp, catch_rows
from host.design.discrete import DiscreteController, controller_ss, force_limit
from sim.params import RobotParams, load_params
from sim.plant import linear_model

__all__ = [
    "VERSION",
    "EST_FULL",
    "EST_REDUCED",
    "ESTIMATORS",
    "filter_gain",
    "SMALL_MAX",
    "LAYOUT",
    "Row",
    "FixedDesign",
    "export",
    "crc16",
    "render",
    "render_default",
]

VERSION = 2  # 2: the EST table (issue 27 item 3)
SMALL_MAX = 2**30 - 1  # largest small int on a 32-bit MicroPython
SHIFT_MAX = 24  # longest shift used (keeps 2**(S-1) and the gains modest)
# Default clamps of the speed estimates (m/s, rad/s).  Not physical speeds: the estimates
# of a noisy measurement (the report's white noise, 71 mm / 0.07 rad rms per 2 ms tick)
# swing far beyond them, and a clamp that bites makes the loop nonlinear (the firmware
# lost the pendulum at 3.6 m/s / 30 rad/s).  The headroom proof holds at these limits.
V_LIMIT = 16.0
W_LIMIT = 120.0
MARGIN = 2**16  # headroom kept below 2**30-1 so the firmware's conservative re-check agrees
DUTY_MAX = 32767
INTEG_SHIFT = 6  # the integrator accumulates (r - x) >> 6 per tick
TEL_SHIFT = 14  # longest telemetry conversion shift
REF_UM_MAX = 1_000_000  # largest |reference| in um the firmware converts (1 m)
TILT_MRAD_MAX = 1500  # largest tilt limit parameter (mrad)
TELEM_UNITS = (1e-4, 1e-3, 1e-4, 1e-3, 1e-2)  # msgtable TELEM_STATE x, xdot, phi, phidot; TELEM_CTRL force

# (name, length) of each table in the flat list; "D" = delay_steps
LAYOUT: tuple[tuple[str, int | str], ...] = (
    ("HDR", 3),  # VERSION, D, LEN
    ("RATE", 1),  # loop rate (Hz) the table was designed for
    ("FMT", 5),  # QX, QP, EV, EW, EU
    ("LIM", 4),  # state limits x, xdot, phi, phidot (LSB)
    ("ULIM", 1),  # force limit (LSB)
    ("RLIM", 1),  # reference limit (x LSB)
    ("ILIM", 1),  # integrator limit
    ("YLIM", 2),  # measurement clamps: encoder counts, ADC counts from the offset
    ("M", 8),  # filter gain rows (i, j): M[2*i + j]
    ("SM", 4),
    ("KF", 4),
    ("KB", "D"),
    ("KR", 1),
    ("KI", 1),
    ("SK", 1),
    ("KV", 4),
    ("KVB", "D"),
    ("SKV", 1),
    ("AD", 16),  # (Ad - I) in int units, row-major
    ("BD", 4),
    ("SA", 4),
    ("MOT", 4),  # KDU, KDV, SD, deadband (duty counts)
    ("REF", 2),  # RMUL, RDIV: x LSB = (um * RMUL + RDIV // 2) // RDIV (RDIV = x LSB in nm)
    ("TILT", 2),  # TNUM, TSH: ADC counts = (mrad * TNUM) >> TSH
    ("ENCJ", 1),  # largest plausible encoder step per tick (counts)
    ("CAL", 2),  # ADC counts with the pendulum upright (pot_offset), ADC full scale
    ("TEL", 6),  # telemetry: unit = (v * TEL[j] + 2**(S-1)) >> S, S = TEL[5]
    # catch mode (host/design/catch.py): PHI_ON, PHI_OFF (phi LSB; PHI_ON 0 = off), DU, ULC (u LSB),
    # CPHI, SPHI (clamp centre -(phi * CPHI) >> SPHI, u LSB), UCMAX (|u| bound in catch mode),
    # RSTEP (x LSB per tick: the reference ramp after the hand-back), W_OFF (phidot LSB)
    ("CATCH", 9),
    ("KFC", 4),  # the catch force row, same form and bounds as KF .. KI, SK
    ("KBC", "D"),
    ("KRC", 1),
    ("KIC", 1),
    ("SKC", 1),
    ("EST", 1),  # estimator: 0 the full (Kalman) filter, 1 the reduced-order observer (M rows of x, phi = identity)
)

EST_FULL = 0
EST_REDUCED = 1
ESTIMATORS = {"full": EST_FULL, "reduced": EST_REDUCED}
"""The estimator codes of the ``EST`` table (``upright export --estimator``)."""


def crc16(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE (the protocol's CRC; check value of b"123456789" is 0x29B1)."""
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def filter_gain(ctrl: DiscreteController) -> tuple[np.ndarray, int]:
    """``(M, EST)``: the firmware's filter gain (4, 2) of a controller and its estimator code.

    The full estimator's is its Kalman gain ``ctrl.M``.  A reduced-order controller
    (:class:`host.design.reduced.ReducedOrderController`) runs in the same predictor-corrector
    form with ``M = Sy + Sw Lr``: the rows of x and phi are the identity (the measured states
    are the measurements), the rows of xdot and phidot the observer's ``Lr``.  With
    ``p = Ad xf + Bd b_0`` this is the Gopinath observer exactly: ``p_w - Lr p_y`` is its
    ``z`` (``z' = F z + G y + H b_0``), and ``I - M C`` leaves only the poles of
    ``F = A22 - Lr A12`` (plus two at zero).
    """
    from host.design.reduced import ReducedOrderController

    if isinstance(ctrl, ReducedOrderController):
        ob = ctrl.observer
        return ob.Sy + ob.Sw @ ob.Lr, EST_REDUCED
    M = np.asarray(ctrl.M, dtype=float)
    if ctrl.design == "reduced":  # ReducedOrderController.firmware_form()
        if not np.array_equal(M[[0, 2], :], np.eye(2)):
            raise ValueError("a reduced-order controller's filter rows of x and phi must be the identity")
        return M, EST_REDUCED
    return M, EST_FULL


@dataclass(frozen=True)
class Row:
    """One integer accumulator of the fixed-point step and its worst case.

    ``acc = sum_j gains[j] * in_j + 2**(shift-1)`` with ``|in_j| <= bounds[j]``.
    """

    name: str
    gains: tuple[int, ...]
    bounds: tuple[int, ...]
    shift: int
    exact: tuple[float, ...] = ()
    residual: bool = False

    @property
    def worst(self) -> int:
        """Largest possible ``|acc|`` (abs-sum bound).

        The rounding term is ``2**(shift-1)``; rows with error feedback carry a remainder
        ``0 <= res < 2**shift`` instead.
        """
        if self.residual:
            extra = (1 << self.shift) - 1
        else:
            extra = (1 << (self.shift - 1)) if self.shift > 0 else 0
        return sum(abs(g) * b for g, b in zip(self.gains, self.bounds)) + extra

    @property
    def quant_error(self) -> float:
        """Worst output error (in output LSB) caused by quantising the gains, over all inputs."""
        return float(sum(abs(g / 2**self.shift - c) * b for g, c, b in zip(self.gains, self.exact, self.bounds)))


def _row(name: str, coeffs: Sequence[float], bounds: Sequence[int], shift_max: int = SHIFT_MAX,
         residual: bool = False) -> Row:
    """Quantise a row with the longest shift whose abs-sum bound fits a small int."""
    bounds = tuple(int(b) for b in bounds)
    best = None
    for s in range(0, shift_max + 1):
        g = tuple(int(round(c * 2**s)) for c in coeffs)
        r = Row(name, g, bounds, s, tuple(float(c) for c in coeffs), residual)
        if r.worst <= SMALL_MAX - MARGIN:
            best = r
        else:
            break
    if best is None:
        raise ValueError(f"row {name}: no shift keeps the accumulator within 2**30-1 (bounds {bounds})")
    return best


def _pow2_lsb(limit: float, bits: int = 16) -> int:
    """Exponent E such that ``limit / 2**-E`` is the largest that stays below ``2**bits``."""
    return int(math.floor(math.log2((2**bits - 1) / limit)))


@dataclass
class FixedDesign:
    """The fixed-point controller: formats, limits, integer tables and the headroom rows."""

    params: RobotParams
    ctrl: DiscreteController
    ki: float
    deadband: int
    fmt: dict[str, int]
    lsb: dict[str, float]
    tables: dict[str, list[int]]
    rows: list[Row] = field(default_factory=list)

    @property
    def delay(self) -> int:
        """Delay steps (length of KB and KVB)."""
        return self.ctrl.delay_steps

    def flat(self) -> list[int]:
        """All tables in :data:`LAYOUT` order."""
        out: list[int] = []
        for name, n in LAYOUT:
            vals = self.tables[name]
            want = self.delay if n == "D" else n
            if len(vals) != want:
                raise ValueError(f"table {name}: {len(vals)} entries, layout wants {want}")
            out.extend(int(v) for v in vals)
        return out

    def blob(self) -> bytes:
        """The upload bytes: the flat table as little-endian int32."""
        f = self.flat()
        return struct.pack(f"<{len(f)}i", *f)

    def crc(self) -> int:
        """CRC-16/CCITT-FALSE of :meth:`blob`."""
        return crc16(self.blob())

    def offsets(self) -> dict[str, tuple[int, int]]:
        """Table name -> (offset, length) in the flat list."""
        out, o = {}, 0
        for name, n in LAYOUT:
            ln = self.delay if n == "D" else int(n)
            out[name] = (o, ln)
            o += ln
        return out


def export(
    params: RobotParams | None = None,
    ctrl: DiscreteController | None = None,
    *,
    ki: float = 0.0,
    deadband: int = 0,
    v_limit: float | None = None,
    w_limit: float | None = None,
    catch: CatchDesign | None = CATCH_DEFAULT,
) -> FixedDesign:
    """Quantise a discrete controller into the firmware's integer tables.

    Parameters
    ----------
    params : RobotParams, optional
        Robot parameters (default: the report's robot).
    ctrl : DiscreteController, optional
        Controller (default: ``controller_ss(params)``).
    ki : float
        Integral gain on the cart position error, N/(m*s) (0: no integral action).
    deadband : int
        Motor deadband compensation in duty counts, added in the direction of the force.
    v_limit : float, optional
        Clamp of the cart-speed estimate, m/s (default ``V_LIMIT`` = 16 m/s, about 9x the
        no-load speed).  Noisy position measurements (the report's white-noise scenario:
        71 mm rms per tick) drive the estimate far beyond the physical speed; a limit
        this wide keeps it linear at the cost of a coarser LSB.
    w_limit : float, optional
        Clamp of the tilt-rate estimate, rad/s (default ``W_LIMIT`` = 120 rad/s, for the
        same reason: 0.07 rad rms per tick of angle noise).
    catch : CatchDesign or None
        The catch-mode row for large tilts (:mod:`host.design.catch`), designed on the
        controller's own plant; ``None`` exports it switched off (``PHI_ON = 0``, the
        tracking row's gains and clamp).

    Returns
    -------
    FixedDesign

    Raises
    ------
    ValueError
        If a row cannot be made to fit the small-int range, or on bad arguments.
    """
    p = load_params() if params is None else params
    c = controller_ss(p) if ctrl is None else ctrl
    if not (0 <= deadband <= 4096) or int(deadband) != deadband:
        raise ValueError(f"deadband must be an int in 0..4096 duty counts, got {deadband!r}")
    if not math.isfinite(ki) or ki < 0:
        raise ValueError(f"ki must be finite and >= 0, got {ki!r}")
    d, Ts = c.delay_steps, c.Ts
    m_per_count = 2 * math.pi * p.r_wheel / p.enc_cpr
    rad_per_count = p.pot_range / 2**p.adc_bits
    no_load = p.V_supply * p.r_wheel / (p.kt * p.gear)
    vlim = V_LIMIT if v_limit is None else float(v_limit)
    wlim = W_LIMIT if w_limit is None else float(w_limit)
    if not (math.isfinite(vlim) and vlim > 0 and math.isfinite(wlim) and wlim > 0):
        raise ValueError(f"v_limit and w_limit must be finite and > 0, got {v_limit!r}, {w_limit!r}")
    lim_si = (2.0 * p.track, vlim, math.pi / 2, wlim)

    QX = _pow2_lsb(lim_si[0] / m_per_count)
    QP = _pow2_lsb(lim_si[2] / rad_per_count)
    EV = _pow2_lsb(lim_si[1])
    EW = _pow2_lsb(lim_si[3])
    # the force format spans the drive's whole range (its LSB is about one duty count); the
    # controller's clamp u_max, usually well inside it, is an integer limit in that format.
    # A format fitted to a small clamp would make the LSB finer than the duty can express
    # and cost the force row its shift (the stored-force gains kb_i < 1 would be coarse)
    uc_si = catch_clamp(p, catch) if catch is not None else c.u_max
    EU = _pow2_lsb(max(c.u_max, uc_si, force_limit(p)))
    s = np.array([m_per_count / 2**QX, 2.0**-EV, rad_per_count / 2**QP, 2.0**-EW])
    su = 2.0**-EU
    LIM = [int(math.floor(lim_si[i] / s[i])) for i in range(4)]
    ULIM = int(math.floor(c.u_max / su))
    ULC = int(math.floor(uc_si / su))
    # catch mode clamps the cart acceleration: u in [-ULC, ULC] - cphi * phi (linear model,
    # cphi = A[1,2] / B[1] N/rad), its centre bounded by the shift at phi = +-pi/2
    A_lin, B_lin, _, _ = linear_model(p)
    cphi_si = float(A_lin[1, 2] / B_lin[1, 0])
    rphi = _row("catch clamp", [cphi_si * s[2] / su], [LIM[2]])
    UCMAX = ULC + (rphi.worst >> rphi.shift) + 1
    UB = max(ULIM, UCMAX)  # bound of a stored force (either row's clamp)
    RLIM = int(math.floor(p.track / s[0]))
    ILIM = 2**16
    YLIM = [LIM[0] >> QX, LIM[2] >> QP]
    # bounds of the accumulator inputs
    EB = [2 * LIM[0], 2 * LIM[2]]  # innovations

    rows: list[Row] = []
    M_int, SM = [], []
    s_meas = (s[0], s[2])
    Mf, est = filter_gain(c)
    for i in range(4):
        r = _row(f"filter[{i}]", [Mf[i, j] * s_meas[j] / s[i] for j in range(2)], EB, residual=True)
        rows.append(r)
        M_int += list(r.gains)
        SM.append(r.shift)
    Kf, kb = c.Kf[0], c.kb
    integ_lsb = 2**INTEG_SHIFT * s[0] * Ts  # m*s per integrator LSB
    coeffs_u = [-Kf[j] * s[j] / su for j in range(4)] + [-kb[i] for i in range(d)] + [c.kr * s[0] / su, math.copysign(ki, c.kr) * integ_lsb / su]
    ru = _row("force", coeffs_u, LIM + [UB] * d + [RLIM, ILIM])
    rows.append(ru)
    if catch is not None:
        kfc, kbc, krc = catch_rows(c, catch)
        coeffs_c = [-kfc[j] * s[j] / su for j in range(4)] + [-kbc[i] for i in range(d)] + [krc * s[0] / su, 0.0]
        CATCH = [int(round(catch.phi_on / s[2])), int(round(catch.phi_off / s[2])), int(round(catch.du / su)), ULC]
    else:
        coeffs_c = coeffs_u
        CATCH = [0, 0, 0, ULC]
    rstep = int(round(catch.r_rate * Ts / s[0])) if catch is not None else 0
    w_off = int(round(catch.w_off / s[3])) if catch is not None else 0
    CATCH += [rphi.gains[0], rphi.shift, UCMAX, max(rstep, 1 if catch is not None else 0), w_off]
    rc = _row("catch force", coeffs_c, LIM + [UB] * d + [RLIM, ILIM])
    rows += [rc, rphi]
    Phi = np.linalg.matrix_power(c.Ad, d)
    gam = [(np.linalg.matrix_power(c.Ad, d - 1 - i) @ c.Bd)[1, 0] for i in range(d)]
    rv = _row("speed", [Phi[1, j] * s[j] / s[1] for j in range(4)] + [g * su / s[1] for g in gam], LIM + [UB] * d)
    rows.append(rv)
    AD, BD, SA = [], [], []
    Adm = c.Ad - np.eye(4)
    for i in range(4):
        r = _row(f"update[{i}]", [Adm[i, j] * s[j] / s[i] for j in range(4)] + [c.Bd[i, 0] * su / s[i]], LIM + [UB], residual=True)
        rows.append(r)
        AD += list(r.gains[:4])
        BD.append(r.gains[4])
        SA.append(r.shift)
    # force -> duty: V = F R r/(n gear kt) + kt gear xdot / r, duty = V/V_supply * 32767
    kdu = p.R * p.r_wheel / (p.n_motors * p.gear * p.kt) / p.V_supply * DUTY_MAX * su
    kdv = p.kt * p.gear / p.r_wheel / p.V_supply * DUTY_MAX * s[1]
    rm = _row("duty", [kdu, kdv], [UB, LIM[1]])
    rows.append(rm)
    # reference um -> x LSB by an exact-ish division: r = (um * 1000 + RDIV/2) // RDIV
    rdiv = int(round(s[0] * 1e9))  # x LSB in nm
    rr = Row("reference", (1000,), (REF_UM_MAX,), 0, (1000.0,))
    if rr.worst + rdiv // 2 > SMALL_MAX:
        raise ValueError("reference conversion overflows")
    rows.append(rr)
    rt = _row("tilt", [1e-3 / rad_per_count], [TILT_MRAD_MAX])
    rows.append(rt)
    tel_b = LIM + [UB]
    tel_s = list(s) + [su]
    TEL = []
    tsh = TEL_SHIFT
    while tsh > 0 and any(
        Row("t", (int(round(tel_s[j] / TELEM_UNITS[j] * 2**tsh)),), (tel_b[j],), tsh).worst > SMALL_MAX for j in range(5)
    ):
        tsh -= 1
    for j in range(5):
        g = int(round(tel_s[j] / TELEM_UNITS[j] * 2**tsh))
        rows.append(Row(f"telemetry[{j}]", (g,), (tel_b[j],), tsh, (tel_s[j] / TELEM_UNITS[j],)))
        TEL.append(g)
    TEL.append(tsh)
    counts_per_m = p.enc_cpr / (2 * math.pi * p.r_wheel)
    encj = int(math.ceil(2.0 * no_load * Ts * counts_per_m)) + 2
    tables = {
        "HDR": [VERSION, d, 0],
        "RATE": [int(round(1.0 / Ts))],
        "FMT": [QX, QP, EV, EW, EU],
        "LIM": LIM,
        "ULIM": [ULIM],
        "RLIM": [RLIM],
        "ILIM": [ILIM],
        "YLIM": YLIM,
        "M": M_int,
        "SM": SM,
        "KF": list(ru.gains[:4]),
        "KB": list(ru.gains[4 : 4 + d]),
        "KR": [ru.gains[4 + d]],
        "KI": [ru.gains[5 + d]],
        "SK": [ru.shift],
        "KV": list(rv.gains[:4]),
        "KVB": list(rv.gains[4:]),
        "SKV": [rv.shift],
        "AD": AD,
        "BD": BD,
        "SA": SA,
        "MOT": [rm.gains[0], rm.gains[1], rm.shift, int(deadband)],
        "REF": [1000, rdiv],
        "TILT": [rt.gains[0], rt.shift],
        "ENCJ": [encj],
        "CAL": [int(p.pot_offset), 2 ** int(p.adc_bits) - 1],
        "TEL": TEL,
        "CATCH": CATCH,
        "KFC": list(rc.gains[:4]),
        "KBC": list(rc.gains[4 : 4 + d]),
        "KRC": [rc.gains[4 + d]],
        "KIC": [rc.gains[5 + d]],
        "SKC": [rc.shift],
        "EST": [est],
    }
    fd = FixedDesign(
        params=p, ctrl=c, ki=ki, deadband=int(deadband),
        fmt={"QX": QX, "QP": QP, "EV": EV, "EW": EW, "EU": EU},
        lsb={"x": s[0], "xdot": s[1], "phi": s[2], "phidot": s[3], "u": su, "integ": integ_lsb},
        tables=tables, rows=rows,
    )
    tables["HDR"][2] = len(fd.flat())
    return fd


def _fmt_list(vals: Sequence[int]) -> str:
    return "(" + ", ".join(str(int(v)) for v in vals) + ("," if len(vals) == 1 else "") + ")"


def render(fd: FixedDesign, source: str = "host/design/export.py") -> str:
    """Text of the generated ``firmware/gains.py`` for a fixed-point design."""
    p, c = fd.params, fd.ctrl
    est = "reduced-order observer" if fd.tables["EST"][0] == EST_REDUCED else "full (Kalman)"
    lines = [
        f"# GENERATED by {source} from {Path(p.source).name if p.source != '<dict>' else p.source} -- do not edit.",
        "# Regenerate with `upright generate` (tests/test_generated.py fails when this is stale).",
        "#",
        f"# Discrete controller: design={c.design}, estimator={est}, Ts={c.Ts:g} s, delay={c.delay_steps} ticks, u_max={c.u_max:.6g} N,",
        f"# K={np.array2string(c.K[0], precision=5, separator=', ')}, kr={c.kr:.6g}, ki={fd.ki:g} N/(m s), deadband={fd.deadband}.",
    ]
    ob = getattr(c, "observer", None)
    if ob is not None:
        sp = np.log(np.asarray(ob.poles, dtype=complex)) / c.Ts
        lines.append("# Reduced-order observer of xdot, phidot: continuous poles "
                     + ", ".join(f"{v.real:.4g}" + (f"{v.imag:+.4g}j" if abs(v.imag) > 1e-9 else "") for v in sp)
                     + f" rad/s, Lr={np.array2string(ob.Lr.ravel(), precision=5, separator=', ')}.")
    lines += [
        "# Formats (LSB in SI units): " + ", ".join(f"{k}={v:.6g}" for k, v in fd.lsb.items()),
        "# " + ", ".join(f"{k}={v}" for k, v in fd.fmt.items()) + " (x = enc << QX, phi = adc << QP, others 2**-E).",
        "#",
        "# Headroom proof: every accumulator is sum_j G_j*in_j + c with |in_j| <= B_j (inputs clamped",
        "# before use) and c = 2**(S-1) (rounding) or 0 <= c < 2**S (carried remainder, filter/update),",
        "# so |any partial sum, in any order| <= sum_j |G_j|*B_j + c <= 2**30-1:",
        "#   row            shift  worst |acc|   margin to 2**30-1   gain-quantisation error (output LSB, worst)",
    ]
    for r in fd.rows:
        lines.append(f"#   {r.name:<14} {r.shift:>5}  {r.worst:>12}  {SMALL_MAX - r.worst:>18}   {r.quant_error:.3g}")
    lines += [
        "",
        "try:",
        "    from micropython import const",
        "except ImportError:",
        "    def const(x):",
        "        return x",
        "",
        f"VERSION = const({VERSION})",
        f"DELAY = const({fd.delay})",
        f"LENGTH = const({len(fd.flat())})",
        f"CRC = const(0x{fd.crc():04X})",
        "",
        "# (name, length) of each table in FLAT, in order",
        "LAYOUT = (",
    ]
    for name, n in LAYOUT:
        ln = fd.delay if n == "D" else n
        lines.append(f"    ({name!r}, {ln}),")
    lines += [")", "", "FLAT = ("]
    for name, n in LAYOUT:
        vals = fd.tables[name]
        lines.append(f"    # {name}")
        for i in range(0, len(vals), 8):
            lines.append("    " + ", ".join(str(int(v)) for v in vals[i : i + 8]) + ",")
    lines += [")", ""]
    return "\n".join(lines)


def render_default() -> str:
    """``firmware/gains.py`` from the default parameters and design (``upright generate``)."""
    return render(export())
