"""Sweep ranges from a TOML file (``upright sweep --ranges FILE``) instead of the fixed defaults.

The keys are the fields of :class:`host.studies.sweep.Uncertainty`; a key the file leaves out
keeps its default, an unknown key or a bad value is refused with the key named::

    mass = 0.2              # relative half-range of the cart mass and (independently) the pendulum masses
    inertia = 0.3           # relative half-range of the pivot inertia (on top of the mass)
    friction = [0.5, 2.0]   # factor range of the cart friction b (log-uniform)
    motor = 0.1             # relative half-range of the motor resistance R and torque constant kt
    delay = [0.005, 0.020]  # s, measurement delay range (each run: the nearest whole tick)
    tilt = 0.03             # rad, initial tilt range +-tilt (robustness)

``sim/sweep_ranges.toml`` is an example (the issue's wider set).  The ranges are the sweep's
parametrisation of the one uncertainty model: :meth:`host.studies.sweep.Uncertainty.axes` turns
them into :class:`host.design.uncertainty.Axis` objects with their laws, which make the draw.
"""

from __future__ import annotations

import math
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

from sim.params import read_toml

from .sweep import SweepError, Uncertainty

__all__ = ["RangesError", "ranges_from_dict", "load_ranges", "KEYS"]

KEYS = tuple(f.name for f in fields(Uncertainty))
_PAIRS = ("friction", "delay")


class RangesError(ValueError):
    """A bad ranges file; ``key`` names the offending key (``""`` for the file itself)."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}" if key else message)
        self.key = key


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def ranges_from_dict(data: dict[str, Any], source: str = "<dict>", base: Uncertainty | None = None) -> Uncertainty:
    """Validate a parsed ranges mapping on top of ``base`` (default :class:`Uncertainty`'s defaults).

    Raises
    ------
    RangesError
        Unknown key, wrong type or a value :class:`Uncertainty` refuses (the key named).
    """
    out = Uncertainty() if base is None else base
    for k, v in data.items():
        if k not in KEYS:
            raise RangesError(k, f"unknown key (known: {', '.join(KEYS)}) (in {source})")
        if k in _PAIRS:
            if not (isinstance(v, list) and len(v) == 2 and all(_number(x) for x in v)):
                raise RangesError(k, f"expected [lo, hi] (two numbers), got {v!r} (in {source})")
            val: Any = (float(v[0]), float(v[1]))
        else:
            if not _number(v):
                raise RangesError(k, f"expected a number, got {v!r} (in {source})")
            val = float(v)
        try:
            out = replace(out, **{k: val})
        except SweepError as exc:
            raise RangesError(k, f"{exc} (in {source})") from None
    return out


def load_ranges(path: str | Path, base: Uncertainty | None = None) -> Uncertainty:
    """The :class:`Uncertainty` of a ranges file (keys left out keep ``base``'s values).

    Raises
    ------
    RangesError
        Unreadable file, bad TOML, unknown key or bad value.
    """
    data = read_toml(path, "ranges file", lambda msg: RangesError("", msg))
    return ranges_from_dict(data, str(Path(path)), base)
