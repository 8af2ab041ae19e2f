"""Largest recoverable tilt with the firmware's catch mode (``make bench``; issue 15 item 3).

The firmware itself (``firmware/app.py`` with its fixed-point controller and the catch-mode
switch, bit for bit what the board runs) closes the loop around the nonlinear plant
(:class:`sim.plantsim.PlantSim`, 10 ms sensor delay, quantised ADC and encoder), in process
under CPython: the integer arithmetic is the same as MicroPython's, and the HIL tests run the
same code on the MicroPython unix port and the emulated RP2040.  A run from ``phi0`` at rest
*recovers* when no fault latches, the pendulum ends within ``END_BAND`` of upright and
the cart acceleration never exceeds the report's ``a_max`` (5 m/s^2).  Bisection over
``phi0`` gives the largest recoverable tilt, printed next to two bounds: what *any*
controller can right on this robot (:func:`host.design.catch.drive_bound`: the drive's
back-EMF speed limit, the track and ``a_max``, with no delay and the exact state; also with
the track or the drive's limits dropped, to show which binds), and ``atan(a_max/g)`` = 0.47
rad (a cart limited to a_max cannot even hold a larger tilt).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from host.boards.fwharness import StandInHal
from host.design.catch import drive_bound, physical_bound
from host.design.export import FixedDesign, export
from sim.params import RobotParams, load_params
from sim.plantsim import PlantSim
from sim.scenario import Scenario

__all__ = ["TiltRun", "run_tilt", "largest_tilt", "bench", "END_BAND"]

END_BAND = 0.01  # rad: |phi| at the end of a recovered run
DURATION = 5.0  # s


@dataclass(frozen=True)
class TiltRun:
    """One firmware-in-the-loop run from a tilt at rest."""

    phi0: float
    recovered: bool
    faults: int
    phi_end: float
    a_max: float
    x_max: float
    n_catch: int
    handback_s: float  # time of the hand-back to the tracking row (nan: none)
    bump_n: float  # force difference of the two rows at the hand-back (N)
    log: dict[str, np.ndarray]


class _Gains:
    def __init__(self, fd: FixedDesign) -> None:
        from host.design.export import LAYOUT, VERSION

        self.VERSION = VERSION
        self.LAYOUT = tuple((n, fd.delay if ln == "D" else int(ln)) for n, ln in LAYOUT)
        self.FLAT = tuple(fd.flat())
        self.CRC = fd.crc()


def run_tilt(phi0: float, *, fd: FixedDesign | None = None, params: RobotParams | None = None,
             plant: RobotParams | None = None, duration: float = DURATION) -> TiltRun:
    """The firmware (CPython) balancing the nonlinear plant from ``phi0`` rad at rest.

    Parameters
    ----------
    phi0 : float
        Initial tilt (rad), released at rest.
    fd : FixedDesign, optional
        The gain table (default: ``export(params)``, what ``firmware/gains.py`` holds).
    params, plant : RobotParams, optional
        Design and simulated-plant parameters (default: the report's robot for both).
    duration : float
        Simulated time (s).
    """
    from firmware.app import App

    p = load_params() if params is None else params
    fd = export(p) if fd is None else fd
    sc = Scenario(name="catch", duration=duration, x0=(0.0, 0.0, float(phi0), 0.0))
    sim = PlantSim(plant if plant is not None else p, sc)
    hal = StandInHal()  # adc/enc set from the plant, duty read back, 250 us per ticks_us call
    app = App(hal, gains=_Gains(fd), config={"arm_tilt_mrad": 500, "watchdog_ms": 10000, "epoch": 0})
    c = app.ctrl
    su = fd.lsb["u"]
    hal.adc, hal.enc = sim.read()
    app.step()
    app.cmd_arm()
    n = sim.n_ticks
    catching = np.zeros(n, dtype=bool)
    hand, bump = math.nan, math.nan
    for k in range(n):
        hal.adc, hal.enc = sim.read()
        was = c.catching
        app.step()
        catching[k] = c.catching
        if was and not c.catching and math.isnan(hand):
            hand, bump = k * sim.Ts, c.bump * su
        sim.step(hal.duty, u_cmd=c.u_raw * su, u_sat=c.u * su)
    log = sim.result()
    log["catch"] = catching
    phi = log["phi"]
    a = float(np.max(np.abs(log["xddot"])))
    faults = int(app.sup.faults)
    ok = faults == 0 and abs(float(phi[-1])) < END_BAND and a <= float(p.a_max)
    return TiltRun(float(phi0), bool(ok), faults, float(phi[-1]), a, float(np.max(np.abs(log["x"]))),
                   int(c.n_catch), hand, bump, log)


def largest_tilt(*, fd: FixedDesign | None = None, params: RobotParams | None = None, lo: float = 0.1,
                 hi: float | None = None, tol: float = 0.0025) -> tuple[float, list[TiltRun]]:
    """Bisection for the largest tilt at rest the firmware recovers from (``lo`` must recover).

    Returns the largest recovered tilt and every run made.
    """
    p = load_params() if params is None else params
    fd = export(p) if fd is None else fd
    hi = min(0.5, physical_bound(p) + 0.02) if hi is None else hi
    runs = [run_tilt(lo, fd=fd, params=p)]
    if not runs[0].recovered:
        return math.nan, runs
    top = run_tilt(hi, fd=fd, params=p)
    runs.append(top)
    if top.recovered:
        return hi, runs
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        r = run_tilt(mid, fd=fd, params=p)
        runs.append(r)
        if r.recovered:
            lo = mid
        else:
            hi = mid
    return lo, runs


def bench() -> dict[str, Any]:
    """``make bench``: largest recoverable tilt with and without catch mode, next to the bounds."""
    p = load_params()
    t0 = time.perf_counter()
    best, runs = largest_tilt(params=p)
    best_off, runs_off = largest_tilt(fd=export(p, catch=None), params=p, lo=0.05, hi=0.3)
    dt = time.perf_counter() - t0
    r30 = run_tilt(0.30, params=p)
    t1 = time.perf_counter()
    db = drive_bound(p)
    dt_bound = time.perf_counter() - t1
    bound = physical_bound(p)
    rows = [
        {"case": "firmware + catch mode (shipped)", "largest tilt rad": round(best, 4)},
        {"case": "firmware, tracking row only", "largest tilt rad": round(best_off, 4)},
        {"case": f"bound: any controller, a_max, drive (<= {db.v_max:.2f} m/s), track +-{db.x_lim:g} m",
         "largest tilt rad": round(db.phi_max, 4)},
        {"case": "  the same on an endless track", "largest tilt rad": round(db.phi_max_no_track, 4)},
        {"case": "  the same without the drive's limits", "largest tilt rad": round(db.phi_max_no_speed_limit, 4)},
        {"case": "bound: atan(a_max / g) (hold at rest)", "largest tilt rad": round(bound, 4)},
    ]
    return {
        "title": "Largest recoverable tilt at rest (firmware in the loop, CPython, bisection)",
        "rows": rows,
        "notes": [
            f"recovered = no fault, |phi| < {END_BAND} rad after {DURATION:g} s, |xddot| <= {p.a_max:g} m/s^2; "
            f"{len(runs) + len(runs_off)} runs in {dt:.1f} s",
            f"0.30 rad: |a|max {r30.a_max:.2f} m/s^2, cart {r30.x_max:.2f} m, hand-back at {r30.handback_s:.2f} s, "
            f"force step there {r30.bump_n:.3f} N",
            "beyond the largest tilt the cart leaves the track (1.25 m: F_TRACK) or the drive runs out of speed",
            f"bound (host.design.catch.drive_bound, {dt_bound:.1f} s): push as hard as allowed, then brake so the cart "
            f"stops on the separatrix into upright; no delay, exact state, continuous time; at the bound it brakes at "
            f"{db.t_brake:.2f} s from {db.v_peak:.2f} m/s and stops at {db.x_stop:.2f} m, {db.t_stop:.2f} s",
        ],
        "bound_rad": bound,
        "drive_bound_rad": db.phi_max,
        "drive_bound_no_track_rad": db.phi_max_no_track,
        "drive_bound_no_speed_limit_rad": db.phi_max_no_speed_limit,
        "v_max_m_s": db.v_max,
        "largest_rad": best,
        "largest_rad_no_catch": best_off,
    }
