"""Scenarios as data: what happens to the robot during a run, loaded from TOML and validated.

A scenario file (``sim/scenarios/<name>.toml``) has these keys; everything but ``name`` and
``duration`` is optional::

    name = "push_0p2N_5s"            # identifier (letters, digits, _ - .)
    description = "..."              # one line for summaries
    duration = 8.0                   # s, simulated time
    seed = 1                         # seed of the noise generator

    [initial]                        # initial state (default all 0)
    x = 0.0                          # m
    xdot = 0.0                       # m/s
    phi = 0.1                        # rad
    phidot = 0.0                     # rad/s

    [[force]]                        # disturbance forces on the cart, any number
    kind = "push"                    # constant force ...
    start = 0.5                      # s
    duration = 5.0                   # s
    amplitude = 0.2                  # N
    [[force]]
    kind = "impulse"                 # ... or an impulse (a kick)
    time = 0.5                       # s
    impulse = 1.0                    # N*s
    width = 0.0                      # s; 0 = Dirac (a velocity jump), > 0 = rectangular pulse

    [reference]                      # cart position reference (default 0)
    kind = "step"                    # "none", "step" or "square"
    start = 0.5                      # s, first edge
    amplitude = 0.2                  # m, the step / the high level
    duration = 5.0                   # step only: s until it returns to low (default: held)
    period = 4.4                     # square only: s per full cycle (each level held period/2)
    low = 0.0                        # m, the low level

    [noise]                          # measurement noise, see sim.sensors.NoiseModel
    kind = "white"                   # "none", "white" or "uniform"
    power = 1e-5                     # white: PSD height, unit^2*s (variance = power / sample_time)
    sample_time = 0.002              # white: s (default: the control period)
    amplitude = 0.005                # uniform: half-width (rad, m)
    channels = ["x", "phi"]          # noisy channels (default both, as in the report)

    [sensors]
    delay = 0.01                     # s, measurement delay (default: the robot's)

    [params]                         # robot parameter overrides, bare or dotted keys
    M = 0.55

    [expect]                         # what the run must show against the report's constraints
    phi_max = "pass"                 # "pass", "fail" or "any" for each constraint
    settle = "pass"
    a_max = "fail"
    settle_on = ["phi", "x"]         # signals whose settling is measured (default phi, + x with a reference)
    note = "why a constraint is expected to fail"

    [expect.float]                   # overrides for the float simulation only (`upright simulate`):
    settle = "fail"                  # it models the tracking controller, not the firmware's catch mode

Any unknown key, wrong type or out-of-range value raises :class:`ScenarioError` naming the
offending key (``force[1].amplitude``); a bad ``[params]`` entry raises it with the key
``params.<name>``.
"""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Mapping

import numpy as np

from .params import SCHEMA, ParamError, RobotParams, load_params
from .sensors import CHANNELS, NoiseModel

__all__ = [
    "SCENARIO_DIR",
    "REPORT_SCENARIOS",
    "CONSTRAINTS",
    "MODELS",
    "Model",
    "ScenarioError",
    "ForceEvent",
    "Reference",
    "Expectation",
    "Scenario",
    "load_scenario",
    "scenario_from_dict",
    "list_scenarios",
    "dump_scenario",
    "PRECEDENCE",
    "precedence_note",
]

SCENARIO_DIR = Path(__file__).with_name("scenarios")

REPORT_SCENARIOS = (
    "push_0p2N_5s",
    "impulse_kick",
    "tilt_0p1",
    "tilt_0p3",
    "ref_step_20cm",
    "square_wave_20cm_2p2s",
    "white_noise_1e-5_delay10ms",
    "uniform_noise_0p005",
)
"""The report's simulation scenarios (sections 3.2-3.5), in the order of the report."""

CONSTRAINTS = ("phi_max", "settle", "a_max")
"""The report's constraints: peak |phi| < phi_max, settling < t_settle, peak |xddot| <= a_max."""

_NAME = re.compile(r"^[A-Za-z0-9_.\-]+$")
_EXPECT_VALUES = ("pass", "fail", "any")
# what ran: the firmware (HIL on any board) or the float simulation (``[expect.float]``)
Model = Literal["firmware", "float"]
MODELS: tuple[Model, ...] = ("firmware", "float")


class ScenarioError(ValueError):
    """A scenario file or value is invalid.

    Parameters
    ----------
    key : str
        Dotted name of the offending key (``"noise.power"``, ``"force[0].start"``), or ``""``
        for file-level errors.
    message : str
        What is wrong with it.
    """

    def __init__(self, key: str, message: str) -> None:
        self.key = key
        self.message = message
        super().__init__(f"{key}: {message}" if key else message)


@dataclass(frozen=True)
class ForceEvent:
    """A disturbance force on the cart.

    ``kind="push"``: ``amplitude`` N from ``start`` for ``duration`` s.
    ``kind="impulse"``: ``impulse`` N*s at ``start``; ``width == 0`` is a Dirac impulse
    (applied as an instantaneous change of the generalised momenta), otherwise a rectangular
    pulse of ``impulse/width`` N lasting ``width`` s.
    """

    kind: str
    start: float
    duration: float = 0.0
    amplitude: float = 0.0
    impulse: float = 0.0
    width: float = 0.0

    @property
    def is_dirac(self) -> bool:
        """True for an impulse of zero width."""
        return self.kind == "impulse" and self.width == 0.0

    @property
    def end(self) -> float:
        """Time the force stops acting (s)."""
        return self.start + (self.duration if self.kind == "push" else self.width)

    def force(self, t: np.ndarray | float) -> np.ndarray:
        """The finite part of the force at time(s) ``t`` (N); 0 for a Dirac impulse."""
        t = np.asarray(t, dtype=float)
        if self.kind == "push":
            return np.where((t >= self.start) & (t < self.end), self.amplitude, 0.0)
        if self.width > 0:
            return np.where((t >= self.start) & (t < self.end), self.impulse / self.width, 0.0)
        return np.zeros_like(t)


@dataclass(frozen=True)
class Reference:
    """Cart position reference ``x_ref(t)`` (m)."""

    kind: str = "none"
    start: float = 0.0
    amplitude: float = 0.0
    duration: float | None = None
    period: float | None = None
    low: float = 0.0

    def __call__(self, t: np.ndarray | float) -> np.ndarray:
        """Reference at time(s) ``t``."""
        t = np.asarray(t, dtype=float)
        if self.kind == "none":
            return np.full_like(t, self.low)
        on = t >= self.start
        if self.kind == "step":
            if self.duration is not None:
                on &= t < self.start + self.duration
        else:  # square: high during the first half of each period
            assert self.period is not None
            phase = np.mod(t - self.start, self.period)
            on &= phase < self.period / 2
        return np.where(on, self.amplitude, self.low)

    def at(self, t: float) -> float:
        """Reference at one time ``t`` (plain float, no numpy: the per-tick fast path)."""
        if self.kind == "none" or t < self.start:
            return self.low
        if self.kind == "step":
            on = self.duration is None or t < self.start + self.duration
        else:
            assert self.period is not None
            on = math.fmod(t - self.start, self.period) < self.period / 2
        return self.amplitude if on else self.low

    def edges(self, until: float) -> list[float]:
        """Times (s) in ``[0, until)`` at which the reference jumps."""
        if self.kind == "none" or self.amplitude == self.low:
            return []
        if self.kind == "step":
            e = [self.start] + ([self.start + self.duration] if self.duration is not None else [])
        else:
            assert self.period is not None
            n = int(math.ceil((until - self.start) / (self.period / 2))) + 1
            e = [self.start + i * self.period / 2 for i in range(max(n, 0))]
        return [v for v in e if 0.0 <= v < until]


@dataclass(frozen=True)
class Expectation:
    """Expected outcome of each constraint check ("pass", "fail" or "any")."""

    phi_max: str = "pass"
    settle: str = "pass"
    a_max: str = "pass"
    settle_on: tuple[str, ...] | None = None
    note: str = ""
    float_overrides: Mapping[str, str] = field(default_factory=dict, hash=False)

    def of(self, constraint: str, model: Model = "firmware") -> str:
        """Expected outcome of ``constraint`` (one of :data:`CONSTRAINTS`).

        Parameters
        ----------
        constraint : str
            One of :data:`CONSTRAINTS`.
        model : str
            ``"firmware"`` (the firmware in HIL, on any board) or ``"float"`` (the float
            simulation of the tracking controller, which has no catch mode); ``[expect.float]``
            overrides apply to the latter only.
        """
        if model not in MODELS:
            raise ValueError(f"model must be one of {', '.join(MODELS)}, got {model!r}")
        if model == "float" and constraint in self.float_overrides:
            return str(self.float_overrides[constraint])
        return str(getattr(self, constraint))


@dataclass(frozen=True)
class Scenario:
    """One validated scenario (see the module docstring for the file format)."""

    name: str
    duration: float
    description: str = ""
    seed: int = 0
    x0: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    forces: tuple[ForceEvent, ...] = ()
    reference: Reference = field(default_factory=Reference)
    noise: NoiseModel = field(default_factory=NoiseModel)
    delay: float | None = None
    param_overrides: Mapping[str, float] = field(default_factory=dict, hash=False)
    expect: Expectation = field(default_factory=Expectation)
    source: str = "<dict>"

    def apply(self, params: RobotParams) -> RobotParams:
        """The robot parameters for this run: ``params`` with the overrides and the delay.

        Raises
        ------
        ScenarioError
            If the scenario does not fit this robot (see :meth:`check`).
        """
        changes = dict(self.param_overrides)
        if self.delay is not None:
            changes["delay"] = self.delay
        try:
            p = params.replace(**changes) if changes else params
        except ParamError as exc:
            key = "sensors.delay" if exc.key == "sensors.delay" and self.delay is not None else f"params.{exc.key}"
            raise ScenarioError(key, f"{exc} (in {self.source})") from None
        self._check_fits(p)
        return p

    def check(self, params: RobotParams) -> None:
        """Check that the scenario fits the robot ``params`` (before any work starts).

        Raises
        ------
        ScenarioError
            ``initial.x`` outside the track (``|x| < loop.track``), or ``sensors.delay`` (or
            the robot's) not a whole number of control ticks at ``loop.rate``.
        """
        self.apply(params)

    def _check_fits(self, p: RobotParams) -> None:
        track = p.track
        if not abs(self.x0[0]) < track:
            raise ScenarioError("initial.x", f"{self.x0[0]:g} m lies outside the track (|x| < {track:g} m, "
                                             f"loop.track) (in {self.source})")
        for edge in (self.reference.amplitude, self.reference.low):
            if self.reference.kind != "none" and not abs(edge) < track:
                raise ScenarioError("reference.amplitude" if edge == self.reference.amplitude else "reference.low",
                                    f"{edge:g} m lies outside the track (|x| < {track:g} m) (in {self.source})")

    def disturbance(self, t: np.ndarray | float) -> np.ndarray:
        """Finite disturbance force at time(s) ``t`` (N), Dirac impulses excluded."""
        t = np.asarray(t, dtype=float)
        total = np.zeros_like(t)
        for f in self.forces:
            total = total + f.force(t)
        return total

    def dirac_impulses(self, t0: float, t1: float) -> list[tuple[float, float]]:
        """Dirac impulses ``(time, N*s)`` with ``t0 <= time < t1``."""
        return [(f.start, f.impulse) for f in self.forces if f.is_dirac and t0 <= f.start < t1]

    def x_ref(self, t: np.ndarray | float) -> np.ndarray:
        """Cart position reference at time(s) ``t`` (m)."""
        return self.reference(t)

    def events(self) -> list[float]:
        """Times (s) at which the system is disturbed: 0, force on/off, reference edges."""
        ev = {0.0}
        for f in self.forces:
            ev.add(f.start)
            if f.end > f.start:
                ev.add(f.end)
        ev.update(self.reference.edges(self.duration))
        return sorted(v for v in ev if 0.0 <= v < self.duration)

    @property
    def settle_on(self) -> tuple[str, ...]:
        """Signals whose settling time is measured."""
        if self.expect.settle_on is not None:
            return self.expect.settle_on
        return ("phi", "x") if self.reference.kind != "none" else ("phi",)

    @property
    def noisy(self) -> bool:
        """True if the run has measurement noise."""
        return self.noise.kind != "none"


# ------------------------------------------------------------------ parsing helpers
def _num(d: Mapping[str, Any], key: str, where: str, default: float | None = None, *, lo: float | None = None,
         lo_open: bool = False, hi: float | None = None) -> float:
    name = f"{where}.{key}" if where else key
    if key not in d:
        if default is None:
            raise ScenarioError(name, "missing")
        return default
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ScenarioError(name, f"expected a number, got {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise ScenarioError(name, f"must be finite, got {v!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise ScenarioError(name, f"must be {'>' if lo_open else '>='} {lo:g}, got {v!r}")
    if hi is not None and v > hi:
        raise ScenarioError(name, f"must be <= {hi:g}, got {v!r}")
    return v


def _choice(d: Mapping[str, Any], key: str, where: str, choices: tuple[str, ...], default: str | None = None) -> str:
    name = f"{where}.{key}" if where else key
    if key not in d:
        if default is None:
            raise ScenarioError(name, f"missing (one of {', '.join(choices)})")
        return default
    v = d[key]
    if v not in choices:
        raise ScenarioError(name, f"must be one of {', '.join(choices)}, got {v!r}")
    return str(v)


def _only(d: Mapping[str, Any], allowed: tuple[str, ...], where: str) -> None:
    for k in d:
        if k not in allowed:
            name = f"{where}.{k}" if where else k
            raise ScenarioError(name, f"unknown key (expected one of {', '.join(allowed)})")


def _table(data: Mapping[str, Any], key: str, where: str = "") -> Mapping[str, Any]:
    v = data.get(key, {})
    if not isinstance(v, Mapping):
        raise ScenarioError(f"{where}.{key}" if where else key, "expected a table")
    return v


def _strings(v: Any, name: str, allowed: tuple[str, ...]) -> tuple[str, ...]:
    if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
        raise ScenarioError(name, f"expected a list of strings, got {v!r}")
    bad = [s for s in v if s not in allowed]
    if bad:
        raise ScenarioError(name, f"unknown entries {bad} (expected among {', '.join(allowed)})")
    return tuple(v)


def _force(d: Any, i: int) -> ForceEvent:
    where = f"force[{i}]"
    if not isinstance(d, Mapping):
        raise ScenarioError(where, "expected a table")
    kind = _choice(d, "kind", where, ("push", "impulse"))
    if kind == "push":
        _only(d, ("kind", "start", "duration", "amplitude"), where)
        return ForceEvent(
            kind,
            start=_num(d, "start", where, lo=0.0),
            duration=_num(d, "duration", where, lo=0.0, lo_open=True),
            amplitude=_num(d, "amplitude", where),
        )
    _only(d, ("kind", "time", "impulse", "width"), where)
    return ForceEvent(
        kind,
        start=_num(d, "time", where, lo=0.0),
        impulse=_num(d, "impulse", where),
        width=_num(d, "width", where, 0.0, lo=0.0),
    )


def _reference(d: Mapping[str, Any]) -> Reference:
    w = "reference"
    kind = _choice(d, "kind", w, ("none", "step", "square"), "none")
    if kind == "none":
        _only(d, ("kind", "low"), w)
        return Reference(low=_num(d, "low", w, 0.0))
    if kind == "step":
        _only(d, ("kind", "start", "amplitude", "duration", "low"), w)
        dur = _num(d, "duration", w, lo=0.0, lo_open=True) if "duration" in d else None
        return Reference(kind, _num(d, "start", w, 0.0, lo=0.0), _num(d, "amplitude", w), dur, None, _num(d, "low", w, 0.0))
    _only(d, ("kind", "start", "amplitude", "period", "low"), w)
    return Reference(kind, _num(d, "start", w, 0.0, lo=0.0), _num(d, "amplitude", w), None,
                     _num(d, "period", w, lo=0.0, lo_open=True), _num(d, "low", w, 0.0))


def _noise(d: Mapping[str, Any]) -> NoiseModel:
    w = "noise"
    kind = _choice(d, "kind", w, ("none", "white", "uniform"), "none")
    allowed = {"none": ("kind",), "white": ("kind", "power", "sample_time", "channels"),
               "uniform": ("kind", "amplitude", "channels")}[kind]
    _only(d, allowed, w)
    chans = _strings(d["channels"], "noise.channels", CHANNELS) if "channels" in d else CHANNELS
    return NoiseModel(
        kind=kind,
        power=_num(d, "power", w, lo=0.0, lo_open=True) if kind == "white" else 0.0,
        amplitude=_num(d, "amplitude", w, lo=0.0, lo_open=True) if kind == "uniform" else 0.0,
        sample_time=_num(d, "sample_time", w, lo=0.0, lo_open=True) if "sample_time" in d else None,
        channels=chans,
    )


def _param_overrides(d: Mapping[str, Any]) -> dict[str, float]:
    out: dict[str, float] = {}
    bare = {k.split(".", 1)[1]: k for k in SCHEMA}
    for k, v in d.items():
        dotted = k if k in SCHEMA else bare.get(k)
        if dotted is None:
            raise ScenarioError(f"params.{k}", "unknown robot parameter")
        out[dotted] = v
    try:
        load_params().replace(**out)  # validate values now, so a bad file fails at load
    except ParamError as exc:
        raise ScenarioError(f"params.{exc.key}", str(exc)) from exc
    return out


def _expect(d: Mapping[str, Any]) -> Expectation:
    w = "expect"
    _only(d, (*CONSTRAINTS, "settle_on", "note", "float"), w)
    vals = {c: _choice(d, c, w, _EXPECT_VALUES, "pass") for c in CONSTRAINTS}
    fl = _table(d, "float", w)
    _only(fl, CONSTRAINTS, "expect.float")
    float_overrides = {c: _choice(fl, c, "expect.float", _EXPECT_VALUES) for c in CONSTRAINTS if c in fl}
    settle_on = _strings(d["settle_on"], "expect.settle_on", CHANNELS) if "settle_on" in d else None
    note = d.get("note", "")
    if not isinstance(note, str):
        raise ScenarioError("expect.note", "expected a string")
    return Expectation(settle_on=settle_on, note=note, float_overrides=float_overrides, **vals)


_TOP = ("name", "description", "duration", "seed", "initial", "force", "reference", "noise", "sensors", "params", "expect")


def scenario_from_dict(data: Mapping[str, Any], source: str = "<dict>") -> Scenario:
    """Validate a parsed TOML mapping into a :class:`Scenario`.

    Raises
    ------
    ScenarioError
        On any unknown, missing or invalid key (``ScenarioError.key`` names it).
    """
    _only(data, _TOP, "")
    name = data.get("name")
    if not isinstance(name, str) or not _NAME.match(name):
        raise ScenarioError("name", f"expected an identifier of letters, digits, _ - ., got {name!r}")
    desc = data.get("description", "")
    if not isinstance(desc, str):
        raise ScenarioError("description", "expected a string")
    duration = _num(data, "duration", "", lo=0.0, lo_open=True, hi=3600.0)
    seed = data.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ScenarioError("seed", f"expected a non-negative integer, got {seed!r}")
    init = _table(data, "initial")
    _only(init, ("x", "xdot", "phi", "phidot"), "initial")
    x0 = (_num(init, "x", "initial", 0.0), _num(init, "xdot", "initial", 0.0),
          _num(init, "phi", "initial", 0.0, lo=-math.pi / 2, hi=math.pi / 2), _num(init, "phidot", "initial", 0.0))
    forces_raw = data.get("force", [])
    if not isinstance(forces_raw, list):
        raise ScenarioError("force", "expected an array of tables ([[force]])")
    forces = tuple(_force(f, i) for i, f in enumerate(forces_raw))
    for i, f in enumerate(forces):
        if f.start >= duration:
            raise ScenarioError(f"force[{i}].{'start' if f.kind == 'push' else 'time'}", f"after the end of the run ({duration:g} s)")
    ref = _reference(_table(data, "reference"))
    noise = _noise(_table(data, "noise"))
    sens = _table(data, "sensors")
    _only(sens, ("delay",), "sensors")
    delay = _num(sens, "delay", "sensors", lo=0.0, hi=0.1) if "delay" in sens else None
    overrides = _param_overrides(_table(data, "params"))
    expect = _expect(_table(data, "expect"))
    return Scenario(name=name, duration=duration, description=desc, seed=seed, x0=x0, forces=forces, reference=ref,
                    noise=noise, delay=delay, param_overrides=overrides, expect=expect, source=source)


def load_scenario(path_or_name: str | Path) -> Scenario:
    """Load a scenario from a TOML file, or by name from ``sim/scenarios/``.

    Parameters
    ----------
    path_or_name : str or Path
        A file path, or a bare name such as ``"tilt_0p1"``.

    Returns
    -------
    Scenario

    Raises
    ------
    ScenarioError
        If the file is missing, not TOML, or invalid (the error names the key).
    """
    p = Path(path_or_name)
    if not p.suffix == ".toml" and p.parent == Path(".") and not p.exists():
        p = SCENARIO_DIR / f"{p.name}.toml"
    try:
        text = p.read_text()
    except OSError as exc:
        known = ", ".join(list_scenarios())
        raise ScenarioError("", f"cannot read scenario {p}: {exc.strerror} (known scenarios: {known})") from exc
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError("", f"{p}: not valid TOML: {exc}") from exc
    try:
        return scenario_from_dict(data, source=str(p))
    except ScenarioError as exc:
        raise ScenarioError(exc.key, f"{exc.message} (in {p})") from None


PRECEDENCE = ("precedence: --params (the design) < --plant FILE (the simulated robot) < the scenario's "
              "[params] and [sensors] delay (the scenario's own perturbation wins)")
"""The rule when a scenario and a plant file both set a value (printed by the CLI)."""


def precedence_note(scenario: Scenario, plant: RobotParams) -> str | None:
    """The :data:`PRECEDENCE` rule and the keys the scenario overrides in the plant file.

    ``None`` when the scenario sets nothing of the robot (no ``[params]``, no ``[sensors]``
    delay).  Every key it sets is listed with the plant file's value and the scenario's,
    e.g. ``pendulum.I 0.0123 -> 0.0160 (scenario)``; keys whose values agree are marked
    ``(same)``.
    """
    changes = dict(scenario.param_overrides)
    if scenario.delay is not None:
        changes["sensors.delay"] = scenario.delay
    if not changes:
        return None
    items = []
    for k, v in changes.items():
        old = plant.values.get(k)
        if old is not None and math.isnan(old):  # derived from the geometry (pendulum.I, L_cm)
            old = getattr(plant, k.split(".", 1)[1])
        same = old is not None and float(old) == float(v)
        items.append(f"{k} {old:g} -> {float(v):g}" + (" (same)" if same else ""))
    return f"{PRECEDENCE}; scenario {scenario.name} overrides the plant file ({plant.source}): " + ", ".join(items)


def list_scenarios() -> list[str]:
    """Names of the scenarios shipped in ``sim/scenarios/`` (report ones first)."""
    names = sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))
    return [n for n in REPORT_SCENARIOS if n in names] + [n for n in names if n not in REPORT_SCENARIOS]


def _fmt(v: Any) -> str:
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, float):
        return repr(v)
    return str(v)


def dump_scenario(s: Scenario) -> str:
    """TOML text that :func:`load_scenario` reads back into an equal scenario (replayable runs)."""
    lines = [f"name = {_fmt(s.name)}", f"description = {_fmt(s.description)}", f"duration = {s.duration!r}",
             f"seed = {s.seed}", "", "[initial]"]
    lines += [f"{k} = {v!r}" for k, v in zip(("x", "xdot", "phi", "phidot"), s.x0)]
    for f in s.forces:
        lines += ["", "[[force]]", f"kind = {_fmt(f.kind)}"]
        if f.kind == "push":
            lines += [f"start = {f.start!r}", f"duration = {f.duration!r}", f"amplitude = {f.amplitude!r}"]
        else:
            lines += [f"time = {f.start!r}", f"impulse = {f.impulse!r}", f"width = {f.width!r}"]
    r = s.reference
    lines += ["", "[reference]", f"kind = {_fmt(r.kind)}", f"low = {r.low!r}"]
    if r.kind != "none":
        lines += [f"start = {r.start!r}", f"amplitude = {r.amplitude!r}"]
        if r.duration is not None:
            lines.append(f"duration = {r.duration!r}")
        if r.period is not None:
            lines.append(f"period = {r.period!r}")
    n = s.noise
    lines += ["", "[noise]", f"kind = {_fmt(n.kind)}"]
    if n.kind == "white":
        lines.append(f"power = {n.power!r}")
        if n.sample_time is not None:
            lines.append(f"sample_time = {n.sample_time!r}")
    if n.kind == "uniform":
        lines.append(f"amplitude = {n.amplitude!r}")
    if n.kind != "none":
        lines.append(f"channels = {_fmt(n.channels)}")
    if s.delay is not None:
        lines += ["", "[sensors]", f"delay = {s.delay!r}"]
    if s.param_overrides:
        lines += ["", "[params]"] + [f'"{k}" = {_fmt(v)}' for k, v in s.param_overrides.items()]
    e = s.expect
    lines += ["", "[expect]"] + [f"{c} = {_fmt(e.of(c))}" for c in CONSTRAINTS]
    if e.settle_on is not None:
        lines.append(f"settle_on = {_fmt(e.settle_on)}")
    if e.note:
        lines.append(f"note = {_fmt(e.note)}")
    if e.float_overrides:
        lines += ["", "[expect.float]"] + [f"{c} = {_fmt(v)}" for c, v in e.float_overrides.items()]
    return "\n".join(lines) + "\n"
