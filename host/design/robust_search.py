"""The robust design search: the candidate whose worst case over the uncertainty set is best.

Candidates (:class:`host.design.robust.Candidate`) are drawn log-uniformly around the shipped
design -- LQR weights ``Q = diag(q_x, q_xdot, q_phi, q_phidot)`` with ``R`` fixed (only the
ratio Q/R matters), the estimator's speed factor and the force clamp -- in two stages: the
shipped design and random candidates (the first ~60 % of the budget), then random
perturbations of the best so far.  Each is scored by :func:`host.design.robust.evaluate` on
the batch scenarios at every point of the set (common points for all: a fair comparison);
the five best and the shipped design then also get the push at their worst robots (the
search ran it at the nominal one only) and are ranked again.  The ranking key is
:attr:`host.design.robust.Evaluation.rank`: a design that fails on the nominal robot, or that
the fixed-point table carries less precisely than ``FORCE_LSB_MAX``, ranks after every one that
does not; then the worst constraint ratio over all points and scenarios (capped at a fall), the
number of robots where the pendulum is lost, the number of robots with a failing check and the
mean ratio.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from sim.params import RobotParams

from .robust import Candidate, Evaluation, UncertaintySet, evaluate, shipped

__all__ = ["random_candidates", "perturb", "search"]

_BOUNDS = {"q_x": (0.2, 10.0), "q_xdot": (0.005, 2.0), "q_phi": (0.01, 3.0), "q_phidot": (0.001, 0.5),
           "observer": (0.25, 4.0), "a_cmd": (3.5, 4.9)}


def _logu(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def random_candidates(n: int, seed: int = 0, R: float = 0.01) -> list[Candidate]:
    """``n`` random candidates (log-uniform weights and observer factor, uniform clamp)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        q = (_logu(rng, *_BOUNDS["q_x"]), 0.0 if rng.random() < 0.5 else _logu(rng, *_BOUNDS["q_xdot"]),
             _logu(rng, *_BOUNDS["q_phi"]), _logu(rng, *_BOUNDS["q_phidot"]))
        out.append(Candidate(f"rand{i}", q, R, _logu(rng, *_BOUNDS["observer"]),
                             float(rng.uniform(*_BOUNDS["a_cmd"]))))
    return out


def perturb(c: Candidate, rng: np.random.Generator, name: str, scale: float = 0.5) -> Candidate:
    """A random neighbour of ``c``: each weight and the observer factor times ``exp(N(0, scale))``."""
    q = tuple(float(v * math.exp(rng.normal(0.0, scale))) for v in c.Q)
    obs = float(np.clip(c.observer * math.exp(rng.normal(0.0, scale)), *_BOUNDS["observer"]))
    a = float(np.clip(c.a_cmd + rng.normal(0.0, 0.25), *_BOUNDS["a_cmd"]))
    return Candidate(name, q, c.R, obs, a)  # type: ignore[arg-type]


def search(params: RobotParams, uset: UncertaintySet, candidates: int = 16, *, seed: int = 0,
           engine: str | None = None, progress: Callable[[int, int, Evaluation], None] | None = None,
           push: bool = True, finalists: int = 5) -> list[Evaluation]:
    """Search for the design with the best worst case over ``uset``.

    Parameters
    ----------
    params : RobotParams
        The design model.
    uset : UncertaintySet
    candidates : int
        Designs evaluated (>= 1; the first is the shipped design).
    seed : int
        Seed of the candidate draw.
    engine : str, optional
        Batch engine.
    progress : callable, optional
        ``progress(done, total, evaluation)`` after each candidate.
    push : bool
        Run the push (scenario simulator) at the worst robots too for the ``finalists`` best
        and the shipped design, and rank the finalists again.

    Returns
    -------
    list of Evaluation
        Every candidate, best first.
    """
    if candidates < 1:
        raise ValueError(f"candidates must be >= 1, got {candidates}")
    rng = np.random.default_rng(seed)
    pts = uset.points(float(params.rate), params.delay)
    n_rand = max(0, int(round(0.6 * (candidates - 1))))
    pool = [shipped(), *random_candidates(n_rand, seed)]
    evals: list[Evaluation] = []

    def run(c: Candidate) -> None:
        try:
            evals.append(evaluate(params, c, uset, push=False, engine=engine, points=pts))
        except (ValueError, np.linalg.LinAlgError):
            return  # a weight set the Riccati solver refuses: not a candidate
        if progress is not None:
            progress(len(evals), candidates, evals[-1])

    for c in pool:
        run(c)
    k = 0
    while len(pool) < candidates:
        best = min(evals, key=lambda e: e.rank).candidate
        c = perturb(best, rng, f"local{k}")
        k += 1
        pool.append(c)
        run(c)
    evals.sort(key=lambda e: e.rank)
    if push:
        # the finalists and the shipped design get the push at their worst robots too (the
        # search ran it at the nominal one only), and the finalists are ranked again
        top = evals[:max(1, finalists)]
        for e in {**{id(e): e for e in top}, **{id(e): e for e in evals if e.candidate.name == "shipped"}}.values():
            e.metrics.update(evaluate(params, e.candidate, uset, push=True, engine=engine, points=pts).metrics)
        evals[:len(top)] = sorted(top, key=lambda e: e.rank)
    return evals
