"""Per-run metrics, the check against the report's constraints, and a terminal summary table.

Metrics (computed from a run log, :data:`sim.plantsim.LOG_COLUMNS`, on the *true* states):

settling time (2 % band)
    The run is cut into segments at the scenario's events (t = 0, force on/off, reference
    edges).  In each segment, for each signal in ``scenario.settle_on`` (``phi``, plus ``x``
    when the reference moves), the final value ``s_f`` is the mean of the segment's last 5 %
    and the band is ``max(2 % of the excursion, floor)`` -- the excursion being the largest
    ``|s - s_f|`` in the segment or the reference step, whichever is larger, and the floor
    two sensor counts (2 ADC counts = 2.3 mrad for phi, 2 encoder counts = 0.31 mm for x), so
    that a tiny response is not asked to settle below what the sensors resolve.  The
    settling time is the time from the segment's start to the first sample after which the
    signal stays in the band; the run's settling time is the worst over segments and
    signals.  A signal still outside the band at the end of its segment has not settled
    (``nan``), nor has a pendulum lying past the tilt constraint at the end of a segment.  With measurement noise the true state never settles in a 2 % band, so the
    settling time is not defined (``nan``, check "N/A") unless the scenario also has events.
peak |phi|
    ``max |phi|`` over the run (rad).
overshoot
    With a moving reference: the largest overshoot of ``x`` past a reference step, in % of
    the step.  Otherwise: the largest excursion of ``phi`` with the opposite sign of its first
    peak, in % of that peak (how far the pendulum swings through upright).
peak cart acceleration, peak force
    ``max |xddot|`` (m/s^2, at the tick instants; a Dirac kick's velocity jump is not an
    acceleration sample) and ``max |force|`` of the motor (N).
time in saturation
    Time (s) during which the duty is at full scale or the controller's force command was
    clipped to ``u_max``.
RMS phi
    ``sqrt(mean(phi^2))`` over the run (rad) -- the noise figure.
steady-state cart error
    ``mean |x - x_ref|`` over the last 0.5 s (m).

Constraints (report 2.2 / 3.1, values from the robot file): ``peak |phi| < phi_max``
(0.3 rad), ``settling < t_settle`` (2.5 s), ``peak |xddot| <= a_max`` (5 m/s^2).  Each check
is PASS, FAIL or N/A, and is compared with the scenario's ``[expect]``.
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import asdict, dataclass
from typing import Mapping, Sequence

import numpy as np

from .motor import DUTY_MAX
from .params import RobotParams
from .scenario import CONSTRAINTS, Model, Scenario

__all__ = [
    "Metrics",
    "Check",
    "RunSummary",
    "settling_time",
    "compute_metrics",
    "check_constraints",
    "evaluate",
    "summary_table",
    "BAND",
]

BAND = 0.02
"""Settling band, fraction of the excursion."""

_TAIL = 0.05  # fraction of a segment averaged for its final value


@dataclass(frozen=True)
class Metrics:
    """Figures of one run (SI units; ``nan`` where not defined)."""

    settling_time: float
    peak_phi: float
    overshoot: float
    peak_xddot: float
    peak_force: float
    time_saturated: float
    rms_phi: float
    ss_cart_error: float
    duration: float
    noisy: bool = False
    settle_from: float = 0.0  # start (s) of the segment whose settling time is reported
    peak_x: float = math.nan  # max |x| (m), for the track limit (information, not a report constraint)

    def as_dict(self) -> dict[str, float | bool]:
        """The metrics as a plain dict."""
        return asdict(self)


@dataclass(frozen=True)
class Check:
    """One constraint check: ``status`` is "PASS", "FAIL" or "N/A"."""

    name: str
    label: str
    value: float
    limit: float
    unit: str
    status: str
    expected: str = "pass"

    @property
    def as_expected(self) -> bool:
        """True if the outcome matches the scenario's expectation ("any" and N/A always do)."""
        if self.expected == "any" or self.status == "N/A":
            return True
        return self.status.lower() == self.expected


@dataclass(frozen=True)
class RunSummary:
    """Metrics and checks of one named run."""

    name: str
    metrics: Metrics
    checks: tuple[Check, ...]
    note: str = ""  # the scenario's explanation of its expected outcomes

    def as_dict(self) -> dict[str, object]:
        """Plain-data form (JSON-ready): name, metrics, checks, note."""
        return {
            "name": self.name,
            "metrics": self.metrics.as_dict(),
            "checks": [{**asdict(c), "as_expected": c.as_expected} for c in self.checks],
            "note": self.note,
        }

    @property
    def passed(self) -> bool:
        """True if no check failed."""
        return all(c.status != "FAIL" for c in self.checks)

    @property
    def as_expected(self) -> bool:
        """True if every check matches the scenario's expectation."""
        return all(c.as_expected for c in self.checks)


def settling_time(
    t: np.ndarray,
    s: np.ndarray,
    *,
    t0: float | None = None,
    t1: float | None = None,
    final: float | None = None,
    scale: float | None = None,
    band: float = BAND,
    floor: float = 0.0,
) -> float:
    """Time from ``t0`` until ``s`` stays within the band around its final value.

    Parameters
    ----------
    t, s : ndarray
        Sample times and signal.
    t0, t1 : float, optional
        Segment ``[t0, t1)`` (default: the whole record).
    final : float, optional
        Final value (default: mean of the last 5 % of the segment).
    scale : float, optional
        Size of the response the band is a fraction of (default: largest ``|s - final|``).
    band : float
        Band as a fraction of ``scale``.
    floor : float
        Smallest band half-width (signal units).

    Returns
    -------
    float
        Settling time (s); 0 if always in the band; ``nan`` if still outside at the end.
    """
    t = np.asarray(t, dtype=float)
    s = np.asarray(s, dtype=float)
    a = t[0] if t0 is None else t0
    b = t[-1] + 1e-12 if t1 is None else t1
    sel = (t >= a - 1e-12) & (t < b - 1e-12)
    ts, ss = t[sel], s[sel]
    if ts.size == 0:
        return math.nan
    if final is None:
        n_tail = max(1, int(round(_TAIL * ss.size)))
        final = float(np.mean(ss[-n_tail:]))
    dev = np.abs(ss - final)
    width = max(band * (float(np.max(dev)) if scale is None else abs(scale)), floor)
    out = np.nonzero(dev > width)[0]
    if out.size == 0:
        return 0.0
    last = out[-1]
    if last == ts.size - 1:
        return math.nan
    return float(ts[last + 1] - a)


def _floors(params: RobotParams | None) -> dict[str, float]:
    if params is None:
        return {"phi": 0.0, "x": 0.0}
    return {
        "phi": 2.0 * params.pot_range / 2**params.adc_bits,
        "x": 2.0 * 2.0 * math.pi * params.r_wheel / params.enc_cpr,
    }


def compute_metrics(log: Mapping[str, np.ndarray], scenario: Scenario, params: RobotParams | None = None) -> Metrics:
    """Metrics of one run (see the module docstring for the definitions).

    Parameters
    ----------
    log : mapping of arrays
        Run log with at least ``t, x, phi, x_ref, xddot, force, duty``; ``u_cmd, u_sat``
        are used if present.
    scenario : Scenario
        The scenario that was run (events, reference, noise).
    params : RobotParams, optional
        For the sensor-resolution floor of the settling band.

    Returns
    -------
    Metrics
    """
    t = np.asarray(log["t"], dtype=float)
    if t.size < 2:
        raise ValueError("a run log needs at least two ticks")
    Ts = float(t[1] - t[0])
    phi = np.asarray(log["phi"], dtype=float)
    x = np.asarray(log["x"], dtype=float)
    xr = np.asarray(log["x_ref"], dtype=float) if "x_ref" in log else np.asarray(scenario.x_ref(t))
    end = float(t[-1] + Ts)
    floors = _floors(params)
    phi_lim = float(params.phi_max) if params is not None else math.inf  # no params: no fallen check
    events = [e for e in scenario.events() if e < end]
    bounds = events + [end]
    edges = set(scenario.reference.edges(end))

    # settling
    settle = math.nan
    settle_from = 0.0
    if not scenario.noisy or len(events) > 1:
        worst = 0.0
        segs = list(zip(bounds[:-1], bounds[1:]))
        if scenario.noisy:
            segs = segs[1:]  # the first segment is pure noise
        for a, b in segs:
            for name in scenario.settle_on:
                sig = phi if name == "phi" else x
                scale = None
                if name == "x" and a in edges:
                    before = float(scenario.x_ref(a - 1e-9)) if a > 0 else 0.0
                    step = float(scenario.x_ref(a)) - before
                    sel = (t >= a) & (t < b)
                    scale = max(abs(step), float(np.max(np.abs(sig[sel] - np.mean(sig[sel][-max(1, int(_TAIL * sel.sum())):])))))
                ts_ = settling_time(t, sig, t0=a, t1=b, scale=scale, floor=floors[name])
                if name == "phi" and abs(float(sig[(t >= a) & (t < b)][-1])) >= phi_lim:
                    ts_ = math.nan  # fell over: "settled" lying down is not settled
                if math.isnan(ts_) or ts_ > worst:
                    settle_from = a
                worst = max(worst, ts_) if not math.isnan(ts_) else math.nan
                if math.isnan(worst):
                    break
            if math.isnan(worst):
                break
        settle = worst

    # overshoot
    overshoot = 0.0
    ref_edges = sorted(edges)
    if ref_edges:
        for i, a in enumerate(ref_edges):
            b = ref_edges[i + 1] if i + 1 < len(ref_edges) else end
            before = float(scenario.x_ref(a - 1e-9)) if a > 0 else 0.0
            new = float(scenario.x_ref(a))
            step = new - before
            if step == 0:
                continue
            sel = (t >= a) & (t < b)
            over = float(np.max((x[sel] - new) * math.copysign(1.0, step)))
            overshoot = max(overshoot, 100.0 * max(0.0, over) / abs(step))
    elif scenario.noisy:
        overshoot = math.nan  # a swing through upright is the noise, not an overshoot
    else:
        k = int(np.argmax(np.abs(phi)))
        # first peak: the largest |phi| before the first sign change after the largest excursion start
        i0 = int(np.nonzero(np.abs(phi) > 0.1 * np.abs(phi[k]))[0][0]) if np.abs(phi[k]) > 0 else 0
        sign0 = np.sign(phi[i0]) if np.abs(phi[k]) > 0 else 0.0
        if sign0 != 0:
            # the first sign change after the excursion starts (an opposite sign before it, e.g. a
            # small swing at t = 0, is not the first peak's end: phi[i0] itself has sign0)
            first = np.nonzero(np.sign(phi[i0:]) == -sign0)[0] + i0
            peak1 = float(np.max(np.abs(phi[i0: first[0]]))) if first.size else float(np.max(np.abs(phi)))
            opp = float(np.max(-sign0 * phi))
            overshoot = 100.0 * max(0.0, opp) / peak1 if peak1 > 0 else 0.0

    # saturation
    duty = np.asarray(log["duty"])
    sat = np.abs(duty) >= DUTY_MAX
    if "u_cmd" in log and "u_sat" in log:
        uc, us = np.asarray(log["u_cmd"], dtype=float), np.asarray(log["u_sat"], dtype=float)
        known = np.isfinite(uc) & np.isfinite(us)
        sat |= known & (np.abs(uc - np.where(known, us, 0.0)) > 1e-9)
    tail = t >= end - 0.5
    return Metrics(
        settling_time=float(settle),
        peak_phi=float(np.max(np.abs(phi))),
        overshoot=float(overshoot),
        peak_xddot=float(np.max(np.abs(np.asarray(log["xddot"], dtype=float)))),
        peak_force=float(np.max(np.abs(np.asarray(log["force"], dtype=float)))),
        time_saturated=float(np.count_nonzero(sat) * Ts),
        rms_phi=float(np.sqrt(np.mean(phi**2))),
        ss_cart_error=float(np.mean(np.abs(x[tail] - xr[tail]))),
        duration=end,
        noisy=scenario.noisy,
        settle_from=float(settle_from),
        peak_x=float(np.max(np.abs(x))),
    )


def check_constraints(metrics: Metrics, params: RobotParams, scenario: Scenario | None = None,
                      model: Model = "firmware") -> tuple[Check, ...]:
    """PASS/FAIL/N/A of the report's three constraints, with the scenario's expectations.

    ``model`` is ``"firmware"`` or ``"float"``: the float simulation is judged against the
    scenario's ``[expect.float]`` overrides (see :meth:`sim.scenario.Expectation.of`).

    Returns
    -------
    tuple of Check
        ``phi_max`` (peak |phi| < phi_max), ``settle`` (settling < t_settle),
        ``a_max`` (peak |xddot| <= a_max), in the order of :data:`sim.scenario.CONSTRAINTS`.
    """
    exp = scenario.expect if scenario is not None else None

    def expected(name: str) -> str:
        return exp.of(name, model) if exp is not None else "pass"

    def st(ok: bool) -> str:
        return "PASS" if ok else "FAIL"

    m = metrics
    if math.isnan(m.settling_time):
        settle_status = "N/A" if m.noisy else "FAIL"
    else:
        settle_status = st(m.settling_time < params.t_settle)
    checks = {
        "phi_max": Check("phi_max", f"|phi|<{params.phi_max:g}", m.peak_phi, params.phi_max, "rad",
                         st(m.peak_phi < params.phi_max), expected("phi_max")),
        "settle": Check("settle", f"Ts<{params.t_settle:g}s", m.settling_time, params.t_settle, "s",
                        settle_status, expected("settle")),
        "a_max": Check("a_max", f"|a|<={params.a_max:g}", m.peak_xddot, params.a_max, "m/s^2",
                       st(m.peak_xddot <= params.a_max), expected("a_max")),
    }
    return tuple(checks[c] for c in CONSTRAINTS)


def evaluate(log: Mapping[str, np.ndarray], scenario: Scenario, params: RobotParams, name: str | None = None,
             model: Model = "firmware") -> RunSummary:
    """Metrics and constraint checks of a run in one call (``model`` as in :func:`check_constraints`)."""
    p = scenario.apply(params)
    m = compute_metrics(log, scenario, p)
    return RunSummary(name or scenario.name, m, check_constraints(m, p, scenario, model), scenario.expect.note)


def _f(v: float, fmt: str) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt)


def summary_table(runs: Sequence[RunSummary], *, title: str | None = None, notes: bool = False) -> str:
    """Render run summaries as a fixed-width terminal table with PASS/FAIL per constraint.

    A check whose outcome differs from the scenario's expectation is marked ``!``; an expected
    FAIL (documented in the scenario's ``[expect] note``) is marked ``*``.  With ``notes``,
    the note of every run with a FAIL is printed under the table (wrapped to 100 columns).
    """
    cols = [
        ("scenario", 28, "<"), ("|phi|max", 8, ">"), ("settle", 6, ">"), ("overshoot", 9, ">"),
        ("|a|max", 7, ">"), ("|F|max", 6, ">"), ("sat s", 5, ">"), ("phi rms", 7, ">"), ("x err", 6, ">"),
    ]
    check_names = []
    for r in runs:
        for c in r.checks:
            if c.label not in check_names:
                check_names.append(c.label)
    head = " ".join(f"{n:{a}{w}}" for n, w, a in cols) + " " + " ".join(f"{n:>11}" for n in check_names)
    lines = []
    if title:
        lines.append(title)
    lines += [head, "-" * len(head)]
    for r in runs:
        m = r.metrics
        cells = [
            r.name[:28], _f(m.peak_phi, ".4f"), _f(m.settling_time, ".2f"), _f(m.overshoot, ".0f") + ("%" if not math.isnan(m.overshoot) else ""),
            _f(m.peak_xddot, ".2f"), _f(m.peak_force, ".1f"), _f(m.time_saturated, ".2f"), _f(m.rms_phi, ".4f"),
            _f(m.ss_cart_error, ".4f"),
        ]
        row = " ".join(f"{v:{a}{w}}" for v, (_, w, a) in zip(cells, cols))
        by = {c.label: c for c in r.checks}
        marks = []
        for n in check_names:
            c = by.get(n)
            if c is None:
                marks.append(f"{'':>11}")
                continue
            flag = "!" if not c.as_expected else ("*" if c.status == "FAIL" else " ")
            marks.append(f"{c.status + flag:>11}")
        lines.append(row + " " + " ".join(marks))
    n_fail = sum(1 for r in runs for c in r.checks if c.status == "FAIL")
    n_unexp = sum(1 for r in runs for c in r.checks if not c.as_expected)
    lines.append("-" * len(head))
    lines.append(f"{len(runs)} runs, {n_fail} constraint FAIL(s) ({n_fail - n_unexp} expected and documented, marked *), "
                 f"{n_unexp} unexpected outcome(s) (marked !)")
    if notes:
        seen: set[str] = set()
        for r in runs:
            if r.note and not r.passed and r.note not in seen:
                seen.add(r.note)
                lines += textwrap.wrap(f"* {r.name}: {r.note}", 100, subsequent_indent="    ")
    return "\n".join(lines)
