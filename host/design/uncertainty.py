"""The uncertainty set of the robust design: a box of factors on the model's values and a delay range.

Loaded from ``sim/uncertainty.toml`` (:data:`UNCERTAINTY_FILE`) or a file that replaces its keys
(:func:`load_uncertainty`); a bad file is refused with the offending key named
(:class:`UncertaintyError`).  :meth:`UncertaintySet.points` gives the robots a design is scored
on: the nominal one, every vertex of the box and seeded random points inside it.

An optional ``[realism]`` table gives plant-realism ranges in the robot file's own units
(``sim/uncertainty_realistic.toml``; docs/parameters.md, "Plant realism"): absolute values, not
factors (the ideal model's are 0).  The nominal point takes every realism value nearest to 0 in
its range, each vertex at its high end (``realism_vertices = "hi"``, the default: the roughest
robot at every corner of the box; ``"all"`` makes each realism range one more axis of the box),
and the random points draw them uniformly.

Every range is an :class:`Axis` that carries its law -- uniform, log-uniform or symmetric about a
centre -- and, for a coupled axis, the axis it multiplies (the sweep's inertia rides on the
pendulum mass).  The box's random points and the Monte Carlo of :mod:`host.studies.sweep`
(:meth:`host.studies.sweep.Uncertainty.axes`) both draw through :meth:`Axis.draw`; the sweep makes
its robots with :func:`scaled_values`: one model of what is uncertain and how it is drawn.
"""

from __future__ import annotations

import itertools
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from sim.params import SCHEMA, RobotParams, read_toml

__all__ = ["UNCERTAINTY_FILE", "in_model", "FACTORS", "LAWS", "ROBOT_KEYS", "Axis", "scaled_values", "UncertaintyError", "Point", "UncertaintySet", "uncertainty_from_dict",
           "load_uncertainty", "REALISM", "UNCERTAINTY_REALISTIC"]

UNCERTAINTY_FILE = Path(__file__).resolve().parents[2] / "sim" / "uncertainty.toml"
"""The default uncertainty set."""

UNCERTAINTY_REALISTIC = UNCERTAINTY_FILE.with_name("uncertainty_realistic.toml")
"""Today's set with plant realism (``[realism]``): ``--uncertainty sim/uncertainty_realistic.toml``."""

FACTORS: dict[str, tuple[str, str]] = {
    "inertia": ("I", "pendulum inertia about the pivot"),
    "cart_mass": ("M", "cart mass"),
    "pendulum_mass": ("m", "pendulum mass (camera and shaft)"),
    "friction": ("b", "cart friction"),
    "supply": ("V_supply", "supply voltage"),
    "motor_constant": ("kt", "motor torque/back-EMF constant"),
}
"""Factor keys of an uncertainty file -> (batch parameter, meaning)."""

REALISM: dict[str, str] = {"coulomb": "cart.coulomb", "stiction": "cart.stiction", "backlash": "motor.backlash",
                           "deadband": "motor.deadband", "duty_min": "motor.duty_min", "pot_inl": "sensors.pot_inl"}
"""Keys of an uncertainty file's ``[realism]`` table -> robot-file key (the batch parameter is the bare
name, :data:`sim.batch.REALISM_KEYS`); ranges in the robot file's units."""

def in_model(params: RobotParams) -> RobotParams:
    """``params`` without its plant realism (every :data:`REALISM` key it sets, at 0): the design model.

    A robot file written by ``upright identify`` or ``upright commission`` carries the Coulomb
    friction, gear play and deadband the cart-only run measured; the table compensates the
    deadband and most of the friction, and the firmware models the play.  A batch evaluation of a
    linear design with that realism in its plant and none of the firmware's compensation in its
    controller judges a robot nobody runs (at 3 mm of play and 0.5 N of Coulomb friction every run
    of the box hunts, and every candidate scores a never-settling 5.0), so a design's box is scored
    on the model the design is for, and the robot's own verification judges the rest.
    """
    zero = {key: 0.0 for key in REALISM.values() if float(params.values.get(key, 0.0)) != 0.0}
    return params.replace(**zero) if zero else params


ROBOT_KEYS: dict[str, tuple[str, ...]] = {
    "inertia": ("I",), "cart_mass": ("M",), "pendulum_mass": ("m_cam", "m_shaft"), "friction": ("b",),
    "supply": ("V_supply",), "motor_constant": ("kt",), "resistance": ("R",),
}
"""Factor keys -> the robot-file values (bare names) they scale; ``resistance`` is the sweep's
(the box leaves the winding resistance at the robot file's value)."""

LAWS = ("uniform", "log-uniform", "symmetric")
"""How an :class:`Axis` maps a uniform ``u`` in [0, 1) to a value."""


@dataclass(frozen=True)
class Axis:
    """One uncertain quantity, its range and its law.

    Parameters
    ----------
    key : str
        A factor key (:data:`ROBOT_KEYS`), ``"delay"`` (s), ``"tilt"`` (rad) or a realism key.
    law : {"uniform", "log-uniform", "symmetric"}
        ``uniform``: ``a + (b - a) u``; ``log-uniform``: ``exp(log a + (log b - log a) u)``;
        ``symmetric``: ``a + b (2u - 1)``, centre ``a`` and half-range ``b`` (about 0: ``b (2u - 1)``).
    a, b : float
        The law's two numbers: ``lo, hi`` or ``centre, half``.
    times : str
        Coupled axis: the quantity is scaled by that axis's factor first, then by this one's
        (mass-coupled inertia: ``I x f_pendulum_mass x f_inertia``); ``""``: independent.
    """

    key: str
    law: str
    a: float
    b: float
    times: str = ""

    def __post_init__(self) -> None:
        if self.law not in LAWS:
            raise UncertaintyError(self.key, f"unknown law {self.law!r} (known: {', '.join(LAWS)})")
        if self.law == "log-uniform" and not 0 < self.a <= self.b:
            raise UncertaintyError(self.key, f"a log-uniform range needs 0 < lo <= hi, got [{self.a:g}, {self.b:g}]")

    @classmethod
    def uniform(cls, key: str, lo: float, hi: float, times: str = "") -> "Axis":
        """``lo + (hi - lo) u``."""
        return cls(key, "uniform", float(lo), float(hi), times)

    @classmethod
    def log_uniform(cls, key: str, lo: float, hi: float, times: str = "") -> "Axis":
        """Uniform in ``log``: a factor as likely halved as doubled."""
        return cls(key, "log-uniform", float(lo), float(hi), times)

    @classmethod
    def symmetric(cls, key: str, centre: float, half: float, times: str = "") -> "Axis":
        """``centre + half (2u - 1)``: a relative half-range about 1, an absolute one about 0."""
        return cls(key, "symmetric", float(centre), float(half), times)

    @property
    def bounds(self) -> tuple[float, float]:
        """``lo, hi`` of the values drawn."""
        if self.law == "symmetric":
            return self.a - self.b, self.a + self.b
        return self.a, self.b

    def draw(self, u: Any) -> Any:
        """The value of uniform(s) ``u`` in [0, 1) (a float or an array, elementwise)."""
        if self.law == "log-uniform":
            return np.exp(np.log(self.a) + (np.log(self.b) - np.log(self.a)) * u)
        if self.law == "symmetric":
            s = 2.0 * u - 1.0
            return self.b * s if self.a == 0.0 else self.a + self.b * s
        return self.a + (self.b - self.a) * u


def scaled_values(params: RobotParams, axes: "Mapping[str, Axis]", factors: Mapping[str, Any]) -> dict[str, Any]:
    """Robot-file values (bare names, :data:`ROBOT_KEYS`) of drawn factors.

    Each value is the robot's times the coupled axis's factor (if any) times its own, in that
    order; a factor key without an axis leaves its values at the robot's.
    """
    out: dict[str, Any] = {}
    for k, names in ROBOT_KEYS.items():
        ax = axes.get(k)
        if ax is None:
            continue
        for name in names:
            v = getattr(params, name)
            if ax.times:
                v = v * factors[ax.times]
            out[name] = v * factors[k]
    return out


_OTHER_KEYS = ("delay", "random", "seed", "push_points", "supply_measured", "realism", "realism_vertices")


class UncertaintyError(ValueError):
    """A bad uncertainty file or value; ``key`` names the offending key."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}" if key else message)
        self.key = key


@dataclass(frozen=True)
class Point:
    """One robot of the uncertainty set: factors on the model's values and a delay in ticks."""

    factors: Mapping[str, float]
    delay_ticks: int
    vertex: bool
    realism: Mapping[str, float] = field(default_factory=dict)

    def label(self, rate: float) -> str:
        """Compact text, e.g. ``inertia x0.5 cart_mass x1.2 ... delay 20 ms``."""
        parts = [f"{k} x{v:.3g}" for k, v in self.factors.items() if v != 1.0]
        parts += [f"{k} {v:.3g}" for k, v in self.realism.items() if v != 0.0]
        parts.append(f"delay {1e3 * self.delay_ticks / rate:.0f} ms")
        return " ".join(parts)

    def overrides(self, params: RobotParams) -> dict[str, float]:
        """Robot-file overrides (scenario ``[params]``) that make this robot from ``params``."""
        f = self.factors
        fm = f.get("pendulum_mass", 1.0)
        minimal = not math.isnan(params.values["pendulum.m"])  # the minimal form: one pendulum mass
        masses = ({"pendulum.m": params.m * fm} if minimal else
                  {"pendulum.m_cam": params.m_cam * fm, "pendulum.m_shaft": params.m_shaft * fm})
        return {
            "cart.M": params.M * f.get("cart_mass", 1.0),
            **masses,
            "pendulum.L_cm": params.L,  # masses scaled together: the centre of mass stays
            "pendulum.I": params.I * f.get("inertia", 1.0),
            "cart.b": params.b * f.get("friction", 1.0),
            "motor.V_supply": params.V_supply * f.get("supply", 1.0),
            "motor.kt": params.kt * f.get("motor_constant", 1.0),
            **{REALISM[k]: float(v) for k, v in self.realism.items()},
        }

    def values(self, params: RobotParams) -> dict[str, float]:
        """Batch parameter values (:data:`sim.batch.VARIED_KEYS`) of this robot."""
        out = {name: float(getattr(params, name)) * self.factors.get(k, 1.0) for k, (name, _) in FACTORS.items()}
        out.update({k: float(v) for k, v in self.realism.items()})
        return out

    def as_dict(self, rate: float) -> dict[str, Any]:
        """JSON-friendly description."""
        return {**{k: float(v) for k, v in self.factors.items()}, **{k: float(v) for k, v in self.realism.items()},
                "delay_s": self.delay_ticks / rate, "vertex": self.vertex}


@dataclass(frozen=True)
class UncertaintySet:
    """Ranges of the robust design (see ``sim/uncertainty.toml``).

    Parameters
    ----------
    factors : mapping of str to (float, float)
        ``lo, hi`` factor on the model's value for each key of :data:`FACTORS`.
    delay : (float, float)
        Measurement delay range (s); both bounds whole numbers of control ticks.
    random : int
        Random points inside the box, on top of the vertices.
    seed : int
        Seed of the random points.
    push_points : int
        Points worst for the batch scenarios at which the push is also run.
    supply_measured : bool
        The firmware measures the motor supply and inverts the motor with it (the default
        board's divider, ``firmware/board.py`` ``VSUP_ADC_PIN``): a supply factor then only
        moves the drive's limits.  ``False``: a board without the divider, whose duty assumes
        the nominal supply (a supply factor is a force-gain and back-EMF-compensation error).
    source : str
        Where the set came from.
    """

    factors: Mapping[str, tuple[float, float]]
    delay: tuple[float, float] = (0.0, 0.02)
    random: int = 32
    seed: int = 0
    push_points: int = 6
    supply_measured: bool = True
    source: str = "<defaults>"
    realism: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    realism_vertices: str = "hi"

    def delay_ticks(self, rate: float) -> tuple[int, int]:
        """The delay bounds in control ticks at ``rate``.

        Raises
        ------
        UncertaintyError
            A bound that is not a whole number of ticks (never rounded silently).
        """
        out = []
        for v in self.delay:
            t = v * rate
            if abs(t - round(t)) > 1e-6:
                raise UncertaintyError("delay", f"{v:g} s is not a whole number of {1e3 / rate:g} ms sensor samples "
                                                f"at {rate:g} Hz (in {self.source})")
            out.append(int(round(t)))
        return out[0], out[1]

    def axes(self) -> dict[str, Axis]:
        """The box's axes: every factor and realism range, uniform and independent."""
        return {k: Axis.uniform(k, lo, hi) for k, (lo, hi) in (*self.factors.items(), *self.realism.items())}

    def points(self, rate: float, nominal_delay: float) -> list[Point]:
        """The nominal robot, the vertices of the box (duplicates removed), then the random points."""
        d_lo, d_hi = self.delay_ticks(rate)
        keys = list(FACTORS)
        axes = [sorted({float(v) for v in self.factors[k]}) for k in keys] + [sorted({d_lo, d_hi})]
        rk = list(self.realism)
        lo_r = {k: float(self.realism[k][0]) for k in rk}
        hi_r = {k: float(self.realism[k][1]) for k in rk}
        nf = len(keys)
        if self.realism_vertices == "all":
            axes += [sorted({lo_r[k], hi_r[k]}) for k in rk]
        nom_r = {k: min(max(0.0, lo_r[k]), hi_r[k]) for k in rk}  # the value nearest the ideal robot's 0
        pts = [Point({k: 1.0 for k in keys}, int(round(nominal_delay * rate)), False, nom_r)]
        for combo in itertools.product(*axes):
            real = dict(zip(rk, combo[nf + 1:])) if self.realism_vertices == "all" else dict(hi_r)
            pts.append(Point(dict(zip(keys, combo[:nf])), int(combo[nf]), True, real))
        rng = np.random.default_rng(self.seed)
        rng_r = np.random.default_rng([self.seed, 1])  # realism from its own stream: the box's draws stay today's
        ax = self.axes()
        for _ in range(self.random):
            f = {k: float(ax[k].draw(rng.random())) for k in self.factors}
            d = int(rng.integers(d_lo, d_hi + 1))  # whole ticks: the bounds are (delay_ticks)
            real = {k: float(ax[k].draw(rng_r.random())) for k in self.realism}
            pts.append(Point(f, d, False, real))
        return pts


def _pair(v: Any, key: str, src: str, lo_bound: float, hi_bound: float) -> tuple[float, float]:
    ok = isinstance(v, list) and len(v) == 2 and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
    if not ok:
        raise UncertaintyError(key, f"expected [lo, hi] (two numbers), got {v!r} (in {src})")
    lo, hi = float(v[0]), float(v[1])
    if not (math.isfinite(lo) and math.isfinite(hi) and lo_bound <= lo <= hi <= hi_bound) or (lo_bound == 0 and key != "delay" and lo <= 0):
        raise UncertaintyError(key, f"expected {lo_bound:g} {'<' if key != 'delay' else '<='} lo <= hi <= {hi_bound:g}, "
                                    f"got [{lo:g}, {hi:g}] (in {src})")
    return lo, hi


def _count(data: Mapping[str, Any], key: str, default: int, src: str, hi: int) -> int:
    v = data.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= hi:
        raise UncertaintyError(key, f"expected an integer in 0..{hi}, got {v!r} (in {src})")
    return v


def _flag(data: Mapping[str, Any], key: str, default: bool, src: str) -> bool:
    v = data.get(key, default)
    if not isinstance(v, bool):
        raise UncertaintyError(key, f"expected true or false, got {v!r} (in {src})")
    return v


def _realism(v: Any, src: str, base: Mapping[str, tuple[float, float]]) -> dict[str, tuple[float, float]]:
    if not isinstance(v, Mapping):
        raise UncertaintyError("realism", f"expected a table of [lo, hi] ranges, got {v!r} (in {src})")
    out = dict(base)
    for k, r in v.items():
        key = f"realism.{k}"
        if k not in REALISM:
            raise UncertaintyError(key, f"unknown key (known: {', '.join(REALISM)}) (in {src})")
        sp = SCHEMA[REALISM[k]]
        ok = isinstance(r, list) and len(r) == 2 and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                         for x in r)
        if not ok:
            raise UncertaintyError(key, f"expected [lo, hi] (two numbers, {sp.unit}), got {r!r} (in {src})")
        lo, hi = float(r[0]), float(r[1])
        if not (math.isfinite(lo) and math.isfinite(hi) and sp.lo <= lo <= hi <= sp.hi):
            raise UncertaintyError(key, f"expected {sp.lo:g} <= lo <= hi <= {sp.hi:g} {sp.unit} ({sp.doc}), "
                                        f"got [{lo:g}, {hi:g}] (in {src})")
        out[k] = (lo, hi)
    return out


def uncertainty_from_dict(data: Mapping[str, Any], source: str = "<dict>", base: "UncertaintySet | None" = None) -> UncertaintySet:
    """Validate a parsed uncertainty mapping; keys it leaves out keep ``base``'s values.

    Raises
    ------
    UncertaintyError
        On an unknown key or a bad value (the key is named).
    """
    known = (*FACTORS, *_OTHER_KEYS)
    for k in data:
        if k not in known:
            raise UncertaintyError(k, f"unknown key (known: {', '.join(known)}) (in {source})")
    b = base
    factors = dict(b.factors) if b is not None else {}
    for k in FACTORS:
        if k in data:
            factors[k] = _pair(data[k], k, source, 0.0, 100.0)
        elif k not in factors:
            raise UncertaintyError(k, f"missing (in {source})")
    delay = _pair(data["delay"], "delay", source, 0.0, 0.1) if "delay" in data else (b.delay if b else (0.0, 0.02))
    return UncertaintySet(
        factors=factors,
        delay=delay,
        random=_count(data, "random", b.random if b else 32, source, 100_000),
        seed=_count(data, "seed", b.seed if b else 0, source, 2**63 - 1),
        push_points=_count(data, "push_points", b.push_points if b else 6, source, 100_000),
        supply_measured=_flag(data, "supply_measured", b.supply_measured if b else True, source),
        source=source,
        realism=_realism(data["realism"], source, b.realism if b else {}) if "realism" in data
        else (dict(b.realism) if b else {}),
        realism_vertices=_choice(data, "realism_vertices", b.realism_vertices if b else "hi", ("hi", "all"), source),
    )


def _choice(data: Mapping[str, Any], key: str, default: str, options: tuple[str, ...], src: str) -> str:
    v = data.get(key, default)
    if v not in options:
        raise UncertaintyError(key, f"expected one of {', '.join(repr(o) for o in options)}, got {v!r} (in {src})")
    return v


def load_uncertainty(path: str | Path | None = None) -> UncertaintySet:
    """The uncertainty set of a TOML file: ``sim/uncertainty.toml`` with the file's keys replacing it.

    Raises
    ------
    UncertaintyError
        Unreadable file, bad TOML, unknown key or bad value (``key`` names it).
    """
    base_data = tomllib.loads(UNCERTAINTY_FILE.read_text())
    base = uncertainty_from_dict(base_data, str(UNCERTAINTY_FILE))
    if path is None:
        return base
    data = read_toml(path, "uncertainty file", lambda msg: UncertaintyError("", msg))
    return uncertainty_from_dict(data, str(Path(path)), base)
