"""``upright report seed``: the numbers the design report publishes, recomputed.

Every value is computed by the toolkit from the parameter file (default: the report's
robot, ``sim/robot.toml``) and printed next to the value the report prints, with the
relative deviation.  ``--json`` prints only our values, as JSON.
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

import control as ct
import numpy as np

from host.design import analysis
from host.design import controllers as design
from sim.params import RobotParams, load_params
from sim.plant import linear_model

# What the report prints (section, value); the single place these numbers are typed in.
REPORT: dict[str, tuple[str, Any]] = {
    "eigenvalues": ("§2.5", [0.0, -0.1396, -4.8787, 4.8540]),
    "tf_phi_num": ("eq. 2.11", [3.3745, 0.0]),
    "tf_phi_den": ("eq. 2.11", [1.0, 0.1644, -23.68, -3.307]),
    "det_wr": ("§2.6", 1.2453e4),
    "rank_wo": ("§2.6", 4),
    "zeta": ("eq. 3.7", 0.627),
    "omega": ("eq. 3.7", 7.59),
    "k_place": ("eq. 3.11", [-180.0737, -65.3276, 199.8242, 40.6161]),
    "k_lqr": ("§3.2.c", [-73.4847, -43.6178, 133.2959, 28.7986]),
    "observer_poles": ("§3.5", [-47.74, -48.74, -49.74, -50.74]),
    "critical_gain": ("§4.4.c", 3.7),
}


def seed_numbers(params: RobotParams) -> dict[str, Any]:
    """Compute every published number of the report from ``params``.

    Returns
    -------
    dict
        Keys as in :data:`REPORT` plus extras (``tf_x_num``, ``tf_x_den``, ``kr_lqr``,
        ``lqr_q``, ``lqr_r``, observability per sensor, ...), JSON-serialisable.
    """
    A, B, C, _ = linear_model(params)
    eig = np.linalg.eigvals(A)
    eig = sorted(eig.real, key=lambda v: (v > 1e-12, -v))  # the report's order: 0, stable, unstable
    tfs = analysis.transfer_functions(params)
    _, det_wr, _ = analysis.controllability(A, B)
    zeta, omega = design.zeta_omega_from_spec(0.08, 0.84)
    k_place = design.place_gain(params)
    k_lqr = design.lqr_gain(params)
    s = ct.tf("s")
    sens = analysis.single_sensor_observability(params)

    def poly(tf: ct.TransferFunction, which: str) -> list[float]:
        arr = tf.num[0][0] if which == "num" else tf.den[0][0]
        return [float(v) for v in np.atleast_1d(np.squeeze(arr))]

    return {
        "eigenvalues": [float(v) for v in eig],
        "tf_phi_num": poly(tfs["phi"], "num"),
        "tf_phi_den": poly(tfs["phi"], "den"),
        "tf_x_num": poly(tfs["x"], "num"),
        "tf_x_den": poly(tfs["x"], "den"),
        "det_wr": det_wr,
        "rank_wo": analysis.observability_rank(A, C),
        "zeta": zeta,
        "omega": omega,
        "k_place": [float(v) for v in k_place],
        "place_poles": [str(p) for p in design.REPORT_PLACE_POLES],
        "k_lqr": [float(v) for v in k_lqr],
        "lqr_q": list(design.REPORT_LQR_Q),
        "lqr_r": design.REPORT_LQR_R,
        "kr_lqr": design.precompensator(params, k_lqr),
        "observer_poles": [float(p.real) for p in design.observer_gain(params, k_place)[1]],
        "critical_gain": design.critical_gain(params, (s + 1) ** 2 / s),
        "single_sensor": [
            {"model": o.model, "sensor": o.sensor, "rank": o.rank, "observable": o.observable, "gramian_det_1s": o.volume}
            for o in sens
        ],
        "parameters": {k: float(v) for k, v in params.physical.items()},
    }


def _flat(v: Any) -> list[float]:
    return [float(x) for x in np.atleast_1d(np.asarray(v, dtype=float)).ravel()]


def deviation(ours: Any, theirs: Any) -> float:
    """Largest relative deviation between two numbers or equal-length lists.

    Entries the report prints as zero are compared absolutely.
    """
    a, b = _flat(ours), _flat(theirs)
    if len(a) != len(b):
        return math.inf
    dev = 0.0
    for x, y in zip(a, b):
        dev = max(dev, abs(x - y) / abs(y) if y else abs(x - y))
    return dev


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright report``."""
    parser.add_argument("what", choices=["seed"], help="which report: 'seed' is the design report the project started from")
    parser.add_argument("--params", metavar="TOML", help="parameter file (default: the report's robot)")
    parser.add_argument("--json", action="store_true", help="print our numbers as JSON only")


def run(args: argparse.Namespace) -> int:
    """Print the report's numbers next to ours (or ours as JSON)."""
    params = load_params(args.params)
    ours = seed_numbers(params)
    if args.json:
        print(json.dumps(ours, indent=2))
        return 0
    print(f"Design report numbers, recomputed from {params.source}\n")
    print(f"{'quantity':16} {'where':9} {'report':>44}  {'upright':>44}  {'deviation':>9}")
    worst = 0.0
    for key, (where, theirs) in REPORT.items():
        dev = deviation(ours[key], theirs)
        worst = max(worst, dev if key != "critical_gain" else dev / 5)
        fmt = lambda v: ", ".join(f"{x:.5g}" for x in _flat(v))  # noqa: E731
        print(f"{key:16} {where:9} {fmt(theirs):>44}  {fmt(ours[key]):>44}  {100 * dev:8.3f}%")
    print(
        "\nLQR weights recovered: Q = diag({}), R = {} (the report's Q was lost from its text).".format(
            ", ".join(f"{q:g}" for q in ours["lqr_q"]), ours["lqr_r"]
        )
    )
    print("Critical gain: the report reads ~3.7 off a Nyquist plot; ours is exact (Routh/bisection).")
    print("Parameter resolution (Table 2.1 vs. the report's own results): docs/parameters.md")
    return 0
