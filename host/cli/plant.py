"""``--plant FILE``: a robot TOML for the simulated plant, the design keeping ``--params``.

Shared by ``simulate``, ``hil``, ``demo`` and ``sweep``.  The plant file is a complete robot
file (``sim/robot.toml`` format); :func:`sim.params.plant_params` checks it against the
design (same ``loop.rate``; the constraints are the design's).  When a scenario also sets
robot values (``[params]``, ``[sensors] delay``), the scenario wins
(:data:`sim.scenario.PRECEDENCE`); the rule and the overridden keys are printed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Sequence, TextIO

__all__ = ["add_plant_argument", "load_plant", "print_precedence"]

HELP = ("robot TOML of the simulated plant when it differs from the design (the design keeps --params / "
        "sim/robot.toml), or a name from sim/plants/ (soft_pendulum, realistic_cart); a scenario's [params] and [sensors] delay "
        "override it (printed)")


PLANT_DIR = Path(__file__).resolve().parents[2] / "sim" / "plants"
"""Shipped plant files, found by bare name (``--plant soft_pendulum``)."""


def resolve(path: str) -> str:
    """A path as given, or a bare name of :data:`PLANT_DIR` (``soft_pendulum``)."""
    p = Path(path)
    if not p.exists() and p.parent == Path(".") and (PLANT_DIR / f"{p.stem}.toml").exists():
        return str(PLANT_DIR / f"{p.stem}.toml")
    return path


def add_plant_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--plant FILE``."""
    parser.add_argument("--plant", metavar="TOML", default=None, help=HELP)


def load_plant(path: str | None, design: Any, stream: TextIO | None = None) -> Any:
    """The plant of ``--plant path`` for ``design`` (``None`` without ``--plant``); prints what applies.

    Raises
    ------
    sim.params.ParamError
        Unreadable or invalid file, or a ``loop.rate`` other than the design's (exit 2).
    """
    if path is None:
        return None
    from sim.params import load_params, plant_params

    stream = sys.stderr if stream is None else stream
    plant, notes = plant_params(design, load_params(resolve(path)))
    diff = [k for k in plant.values if plant.values[k] != design.values[k]
            and not (plant.values[k] != plant.values[k] and design.values[k] != design.values[k])]
    print(f"plant: {path} (design: {design.source}); differs in: {', '.join(diff) or 'nothing'}", file=stream)
    for n in notes:
        print(f"plant: {n}", file=stream)
    return plant


def print_precedence(scenarios: Sequence[Any], plant: Any, stream: TextIO | None = None) -> list[str]:
    """Print the precedence rule and the overridden keys for each scenario that overrides the plant file."""
    if plant is None:
        return []
    from sim.scenario import precedence_note

    stream = sys.stderr if stream is None else stream
    lines = [n for n in (precedence_note(sc, plant) for sc in scenarios) if n]
    for line in lines:
        print(f"plant: {line}", file=stream)
    return lines
