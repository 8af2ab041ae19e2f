"""The forms of a robot file: geometric or minimal physical, and its optional sections.

:func:`sim.params.params_from_dict` calls :func:`normalise` on the parsed TOML before it
validates the keys, and :func:`guard` on the result; :func:`sim.params.load_params` calls
:func:`note_old_keys`.  This module imports nothing of the project (``sim.params`` imports
it), so the errors are raised as the caller's exception class (``ParamError``).

**Two forms of the pendulum** (``[cart]`` ``M``, ``b`` and ``[environment]`` ``g`` in both):

* *geometric* (the report's robot, ``sim/robot.toml``): ``m_cam``, ``m_shaft``, ``L_shaft``,
  ``L_cam``; the centre of mass ``L_cm`` and the inertia are derived from them unless given;
* *minimal physical* (any cart-pole, a textbook's): ``m`` (the whole pendulum), ``L_cm``
  (pivot to centre of mass) and the inertia, ``I_cm`` or ``I_pivot``.

**The inertia is named for its reference point.**  The equations of motion
(:mod:`sim.plant`) use the inertia about the centre of mass, ``I_cm``; the inertia about
the pivot is ``I_pivot = I_cm + m L_cm^2`` (parallel axis).  A file gives one of them;
``I_pivot`` is converted.  The old key ``pendulum.I`` (documented as about the pivot, used
as about the centre of mass) still loads, read as ``I_cm`` -- what the equations always did --
with a one-line note.  Internally the value stays under ``pendulum.I`` (``RobotParams.I``,
``RobotParams.I_cm``).  A geometric file without an inertia uses the report's eq. (2.10)
value as ``I_cm``, as the report does (docs/parameters.md: "A modelling remark").

**Optional sections**: ``[motor]`` (the drive), ``[sensors]`` and ``[loop]`` may be left out;
analysis and design (a force input, ``x`` and ``phi`` measured, no delay unless asked for)
do without them.  Where something needs one -- the force limit of the drive, export, the
firmware, HIL, a simulated sensor -- the first read of one of its keys raises the caller's
error naming the section, in one line.
"""

from __future__ import annotations

import functools
import math
import sys
import tomllib
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

__all__ = ["OPTIONAL_SECTIONS", "GEOMETRIC_KEYS", "MINIMAL_KEYS", "SectionGuard", "normalise", "guard",
           "note_old_keys", "no_attribute", "form_of", "missing_sections"]

OPTIONAL_SECTIONS = ("motor", "sensors", "loop")
"""Sections a robot file may leave out (analysis and design do without them)."""
GEOMETRIC_KEYS = ("m_cam", "m_shaft", "L_shaft", "L_cam")
"""The pendulum of the geometric form (the report's camera on a shaft)."""
MINIMAL_KEYS = ("m", "L_cm")
"""The pendulum of the minimal form, with ``I_cm`` or ``I_pivot``."""
_NEEDED_FOR = {
    "motor": "the drive: force limit, duty conversion, back-EMF",
    "sensors": "the ADC, the encoder and the measurement delay",
    "loop": "the loop rate, the track and the constraints",
}
_DEFAULT_FILE = Path(__file__).with_name("robot.toml")
_NOTED: set[str] = set()

ErrorType = Callable[[str, str], Exception]


def _present(table: Mapping[str, Any], key: str) -> bool:
    v = table.get(key)
    return v is not None and not (isinstance(v, float) and math.isnan(v))


def _number(v: Any) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(float(v))


@functools.lru_cache(maxsize=1)
def _placeholders() -> dict[str, dict[str, Any]]:
    # The default robot's optional sections: they let the validation of the rest run unchanged;
    # guard() hides them, so no value of them is ever read.
    data = tomllib.loads(_DEFAULT_FILE.read_text())
    out = {s: dict(data[s]) for s in OPTIONAL_SECTIONS}
    out["sensors"]["delay"] = 0.0  # a whole number of ticks at any loop rate
    return out


def form_of(pendulum: Mapping[str, Any]) -> str:
    """``"minimal"`` if the pendulum table gives ``m``, else ``"geometric"``."""
    return "minimal" if _present(pendulum, "m") else "geometric"


def _inertia(p: dict[str, Any], error: ErrorType) -> None:
    # I_cm / I_pivot -> the internal "I" (about the centre of mass), in place
    given = [k for k in ("I", "I_cm", "I_pivot") if _present(p, k)]
    if len(given) > 1:
        raise error(f"pendulum.{given[1]}", f"give one inertia, not {' and '.join('pendulum.' + k for k in given)} "
                                            "(I_cm about the centre of mass, I_pivot about the pivot; I is the old "
                                            "name of I_cm)")
    for k in ("I_cm", "I_pivot"):
        if k in p and not _present(p, k):
            p.pop(k)  # nan: "derive it", as for pendulum.I
    if "I_cm" in p:
        v = p.pop("I_cm")
        if not _number(v) or float(v) < 0:
            raise error("pendulum.I_cm", f"must be a finite number >= 0 kg*m^2 (inertia about the centre of mass), "
                                         f"got {v!r}")
        p["I"] = float(v)
    elif "I_pivot" in p:
        v = p.pop("I_pivot")
        if not _number(v) or not float(v) > 0:
            raise error("pendulum.I_pivot", f"must be a finite number > 0 kg*m^2 (inertia about the pivot), got {v!r}")
        m, L = _mass_and_arm(p)
        if m is None or L is None:
            return  # a bad mass or length: the validation names it
        i_cm = float(v) - m * L * L
        if i_cm < -1e-12 * float(v):
            raise error("pendulum.I_pivot", f"must be >= m L_cm^2 = {m * L * L:.6g} kg*m^2 (a point mass at the "
                                            f"centre of mass), got {v!r}")
        p["I"] = max(i_cm, 0.0)


def _mass_and_arm(p: Mapping[str, Any]) -> tuple[float | None, float | None]:
    if form_of(p) == "minimal":
        m = float(p["m"]) if _number(p.get("m")) else None
    else:
        parts = [p.get(k) for k in ("m_cam", "m_shaft")]
        m = float(parts[0]) + float(parts[1]) if all(_number(x) for x in parts) else None
    if _present(p, "L_cm"):
        L = float(p["L_cm"]) if _number(p["L_cm"]) else None
    else:
        g = [p.get(k) for k in GEOMETRIC_KEYS]
        if not all(_number(x) for x in g) or m is None or m <= 0:
            return m, None
        mc, ms, ls, lc = (float(x) for x in g)
        L = (mc * (ls + lc / 2) + ms * ls / 2) / (mc + ms)
    return m, L


def normalise(data: Mapping[str, Any], error: ErrorType) -> tuple[dict[str, Any], frozenset[str]]:
    """The parsed robot file in the form the schema validates, and the sections it leaves out.

    The inertia given as ``I_cm`` or ``I_pivot`` becomes the internal ``pendulum.I`` (about
    the centre of mass); the form's required pendulum keys are checked; every optional
    section the file leaves out is filled with a placeholder that :func:`guard` hides.

    Parameters
    ----------
    data : mapping
        ``{section: {key: value}}`` as parsed from TOML (not modified).
    error : callable
        ``error(key, message)`` builds the exception to raise (``ParamError``).

    Returns
    -------
    data : dict
    missing : frozenset of str
        The optional sections the file leaves out.
    """
    out = dict(data)
    pend = out.get("pendulum")
    if isinstance(pend, Mapping):
        p = dict(pend)
        geo = [k for k in GEOMETRIC_KEYS if _present(p, k)]
        if form_of(p) == "minimal":
            if geo:
                raise error(f"pendulum.{geo[0]}", "the minimal form (pendulum.m, L_cm, I_cm or I_pivot) and the "
                                                 "geometric form (m_cam, m_shaft, L_shaft, L_cam) cannot be mixed")
            for k in GEOMETRIC_KEYS:
                p.pop(k, None)
            if not _present(p, "L_cm"):
                raise error("pendulum.L_cm", "missing (the minimal form gives m, L_cm and I_cm or I_pivot: pivot to "
                                             "centre of mass, m)")
            if not any(_present(p, k) for k in ("I", "I_cm", "I_pivot")):
                raise error("pendulum.I_cm", "missing: the minimal form gives the inertia, I_cm (about the centre of "
                                             "mass) or I_pivot (about the pivot), kg*m^2")
        else:
            p.pop("m", None)
            for k in GEOMETRIC_KEYS:
                if not _present(p, k):
                    raise error(f"pendulum.{k}", "missing (the geometric form gives m_cam, m_shaft, L_shaft and "
                                                 "L_cam; the minimal form m, L_cm and I_cm or I_pivot)")
        _inertia(p, error)
        out["pendulum"] = p
    missing = frozenset(s for s in OPTIONAL_SECTIONS if s not in out)
    for s in missing:
        out[s] = dict(_placeholders()[s])
    if "loop" in missing and "sensors" not in missing:
        out["loop"]["rate"] = 10000  # any delay of 0.1 ms steps is whole ticks; hidden anyway
    return out, missing


class SectionGuard(Mapping[str, float]):
    """The validated values of a robot file that leaves out optional sections.

    Reading a key of a missing section raises the error naming the section; iteration,
    ``len`` and ``in`` see only the keys the file has (so ``dict(values)`` is the file's).
    """

    def __init__(self, values: Mapping[str, float], missing: frozenset[str], source: str, error: ErrorType) -> None:
        self._values = {k: v for k, v in values.items() if k.split(".", 1)[0] not in missing}
        self._hidden = {k.split(".", 1)[1]: k for k in values if k.split(".", 1)[0] in missing}
        self.missing = missing
        self.source = source
        self._error = error

    def missing_error(self, key: str) -> Exception:
        """The error for a read of ``key`` (dotted) of a missing section."""
        sec = key.split(".", 1)[0]
        return self._error(sec, f"section [{sec}] is not in {self.source}, and this needs it ({key}: "
                                f"{_NEEDED_FOR.get(sec, sec)}); the analysis and the design flags of upright design "
                                f"do without it, export, simulation, the firmware and HIL need it (docs/parameters.md)")

    def __getitem__(self, key: str) -> float:
        if key.split(".", 1)[0] in self.missing:
            raise self.missing_error(key)
        return self._values[key]

    def __contains__(self, key: object) -> bool:
        return key in self._values

    def __iter__(self) -> Iterator[str]:
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def __repr__(self) -> str:
        return f"SectionGuard({self._values!r}, missing={sorted(self.missing)})"


def guard(values: dict[str, float], missing: frozenset[str], source: str,
          error: ErrorType) -> Mapping[str, float]:
    """``values`` as they are, or behind a :class:`SectionGuard` when sections are missing."""
    return SectionGuard(values, missing, source, error) if missing else values


def missing_sections(values: Mapping[str, float]) -> frozenset[str]:
    """The optional sections a robot's values leave out (empty for a complete file)."""
    return values.missing if isinstance(values, SectionGuard) else frozenset()


def no_attribute(values: Mapping[str, float], name: str) -> Exception:
    """The exception for ``RobotParams.<name>`` not found among ``values``: a missing section's
    error when ``name`` is one of its keys, else ``AttributeError``."""
    if isinstance(values, SectionGuard) and name in values._hidden:
        return values.missing_error(values._hidden[name])
    return AttributeError(name)


def note_old_keys(data: Mapping[str, Any], source: str) -> None:
    """Print, once per file, a one-line note for the old key ``pendulum.I`` (to stderr)."""
    pend = data.get("pendulum")
    if isinstance(pend, Mapping) and "I" in pend and source not in _NOTED:
        _NOTED.add(source)
        print(f"note: {source}: pendulum.I is read as pendulum.I_cm (inertia about the centre of mass, as the "
              f"equations always used it); rename it I_cm, or give I_pivot = I_cm + m L_cm^2 (docs/parameters.md)",
              file=sys.stderr)
