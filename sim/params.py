"""Physical parameters of the pendulum-on-cart robot, loaded from TOML and validated.

The schema below is the single source of truth for every parameter: its section, key,
unit, admissible range and meaning.  A missing, unknown or non-physical value is an
error that names the offending key (``ParamError.key``).

The default file ``sim/robot.toml`` describes the report's robot with the values that
reproduce the report's numerical results (see ``docs/parameters.md``).

The plant-realism keys (``cart.coulomb``, ``cart.stiction``, ``motor.backlash``,
``motor.deadband``, ``motor.duty_min``, ``sensors.pot_inl``, ``sensors.pot_inl_cycles``) are
optional and default to the report's ideal robot; :data:`REALISM_KEYS` lists them and
``docs/parameters.md`` ("Plant realism") gives their equations.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

from . import robot_file as _robot_file

DEFAULT_PATH = Path(__file__).with_name("robot.toml")

__all__ = ["ParamError", "Spec", "SCHEMA", "REALISM_KEYS", "RobotParams", "load_params", "params_from_dict",
           "plant_params", "DEFAULT_PATH", "read_toml"]


class ParamError(ValueError):
    """A parameter file or value is invalid.

    Parameters
    ----------
    key : str
        Dotted name of the offending key (``"cart.M"``), or ``""`` for file-level errors.
    message : str
        What is wrong with it.
    """

    def __init__(self, key: str, message: str) -> None:
        self.key = key
        super().__init__(f"{key}: {message}" if key else message)


@dataclass(frozen=True)
class Spec:
    """Specification of one parameter: unit, open/closed bounds, doc, default."""

    unit: str
    doc: str
    lo: float | None = None  # lower bound
    hi: float | None = None  # upper bound
    lo_open: bool = True  # lower bound excluded (strictly positive masses, lengths)
    integer: bool = False
    default: float | None = None  # None: required


_P = Spec  # short alias for the table below

# (section, key) -> Spec.  Optional keys carry a default; None as default with
# ``optional`` semantics is expressed by the DERIVED set below.
SCHEMA: dict[str, Spec] = {
    "cart.M": _P("kg", "mass of the cart", 0.0),
    "cart.b": _P("N/(m/s)", "viscous friction coefficient cart-ground", 0.0, lo_open=False),
    "cart.coulomb": _P("N", "Coulomb (sliding) friction force on the moving cart", 0.0, 100.0, lo_open=False,
                       default=0.0),
    "cart.stiction": _P("N", "static friction: the force that breaks the cart loose (below cart.coulomb: "
                             "cart.coulomb)", 0.0, 100.0, lo_open=False, default=0.0),
    "pendulum.m_cam": _P("kg", "mass of the camera head (geometric form)", 0.0, default=math.nan),
    "pendulum.m_shaft": _P("kg", "mass of the shaft (geometric form)", 0.0, default=math.nan),
    "pendulum.L_shaft": _P("m", "length of the shaft (geometric form)", 0.0, default=math.nan),
    "pendulum.L_cam": _P("m", "length of the camera head along the shaft (geometric form)", 0.0, default=math.nan),
    "pendulum.m": _P("kg", "mass of the pendulum (minimal form; sim/robot_file.py)", 0.0, default=math.nan),
    "pendulum.L_cm": _P("m", "pivot to centre of mass (derived from geometry if absent)", 0.0, default=math.nan),
    "pendulum.I": _P("kg*m^2", "inertia about the centre of mass (a file gives I_cm or I_pivot; eq. 2.10 if absent)",
                     0.0, lo_open=False, default=math.nan),
    "environment.g": _P("m/s^2", "gravitational acceleration", 0.0),
    "motor.V_supply": _P("V", "H-bridge supply voltage", 0.0),
    "motor.R": _P("ohm", "armature resistance", 0.0),
    "motor.kt": _P("N*m/A", "torque constant (= back-EMF constant, V*s/rad)", 0.0),
    "motor.gear": _P("-", "gear reduction, motor turns per wheel turn", 0.0),
    "motor.r_wheel": _P("m", "wheel radius", 0.0),
    "motor.n_motors": _P("-", "motors driving the cart in parallel", 0.0, integer=True),
    "motor.backlash": _P("m", "gear backlash, total play between motor and wheel in metres of cart travel",
                         0.0, 0.05, lo_open=False, default=0.0),
    "motor.deadband": _P("-", "H-bridge deadband (dead time x PWM frequency), fraction of full duty "
                              "subtracted from every pulse", 0.0, 0.5, lo_open=False, default=0.0),
    "motor.duty_min": _P("-", "minimum duty the H-bridge switches at, fraction of full duty (narrower pulses "
                              "apply nothing)", 0.0, 0.5, lo_open=False, default=0.0),
    "sensors.adc_bits": _P("bit", "resolution of the angle ADC", 1, 16, lo_open=False, integer=True),
    "sensors.pot_range": _P("rad", "electrical travel of the angle potentiometer", 0.0),
    "sensors.pot_offset": _P("count", "ADC counts read with the pendulum upright", 0, lo_open=False, integer=True),
    "sensors.pot_inl": _P("-", "potentiometer integral nonlinearity, amplitude of a sine over the travel, "
                               "fraction of the ADC full scale", -0.1, 0.1, lo_open=False, default=0.0),
    "sensors.pot_inl_cycles": _P("-", "periods of the nonlinearity's sine over the ADC full scale (0.5: a bow)",
                                 0.0, 20.0, default=1.0),
    "sensors.enc_cpr": _P("count/rev", "encoder counts per wheel revolution", 0, integer=True),
    "sensors.delay": _P("s", "measurement delay", 0.0, 0.1, lo_open=False),
    "loop.rate": _P("Hz", "control loop rate", 0.0, 10000.0, integer=True),
    "loop.track": _P("m", "half-length of the usable track", 0.0),
    "loop.a_max": _P("m/s^2", "cart acceleration constraint", 0.0),
    "loop.phi_max": _P("rad", "tilt constraint", 0.0, math.pi / 2),
    "loop.t_settle": _P("s", "settling-time constraint", 0.0),
    "loop.ref_rate": _P("m/s", "speed at which the firmware moves its reference to a new set-point while "
                             "balancing (a ramp: firmware parameter ref_rate_mm_s); 0: a step", 0.0, 5.0,
                        lo_open=False, default=0.0),
}


REALISM_KEYS = ("cart.coulomb", "cart.stiction", "motor.backlash", "motor.deadband", "motor.duty_min",
                "sensors.pot_inl", "sensors.pot_inl_cycles")
"""The plant-realism keys (docs/parameters.md, "Plant realism"); all optional, the defaults are the ideal robot."""


def _check(key: str, value: Any, spec: Spec) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParamError(key, f"expected a number in {spec.unit}, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ParamError(key, f"must be finite, got {value!r}")
    if spec.integer and v != int(v):
        raise ParamError(key, f"must be an integer, got {value!r}")
    if spec.lo is not None and (v <= spec.lo if spec.lo_open else v < spec.lo):
        rel = ">" if spec.lo_open else ">="
        raise ParamError(key, f"must be {rel} {spec.lo:g} {spec.unit} ({spec.doc}), got {value!r}")
    if spec.hi is not None and v > spec.hi:
        raise ParamError(key, f"must be <= {spec.hi:g} {spec.unit} ({spec.doc}), got {value!r}")
    return int(v) if spec.integer else v


@dataclass(frozen=True)
class RobotParams:
    """Validated robot parameters (SI units).

    The attributes mirror the TOML keys (``cart.M`` becomes ``M``).  The pendulum mass
    ``m``, its centre of mass ``L`` and inertia ``I`` are derived from the geometry
    unless the file gives ``pendulum.L_cm`` / the inertia; a file in the minimal form gives
    ``pendulum.m``, ``L_cm`` and ``I_cm`` or ``I_pivot`` (:mod:`sim.robot_file`).
    """

    values: Mapping[str, float] = field(repr=False)
    source: str = "<dict>"

    def __getattr__(self, name: str) -> float:
        vals = object.__getattribute__(self, "values")
        for k, v in vals.items():
            if k.split(".", 1)[1] == name:
                return v
        raise _robot_file.no_attribute(vals, name)  # a missing section's key: its error

    @property
    def m(self) -> float:
        """Total pendulum mass m_pend = m_cam + m_shaft, or ``pendulum.m`` (kg)."""
        if not math.isnan(self.values["pendulum.m"]):
            return self.values["pendulum.m"]
        return self.values["pendulum.m_cam"] + self.values["pendulum.m_shaft"]

    @property
    def L(self) -> float:
        """Pivot-to-centre-of-mass length L_CM (m)."""
        v = self.values["pendulum.L_cm"]
        if not math.isnan(v):
            return v
        mc, ms = self.values["pendulum.m_cam"], self.values["pendulum.m_shaft"]
        ls, lc = self.values["pendulum.L_shaft"], self.values["pendulum.L_cam"]
        return (mc * (ls + lc / 2) + ms * ls / 2) / (mc + ms)

    @property
    def I(self) -> float:  # noqa: E743 - the report's symbol
        """Pendulum inertia about the centre of mass as the equations use it (kg m^2): the file's
        ``I_cm`` (or ``I_pivot - m L^2``), else eq. (2.10) (the report's choice, docs/parameters.md)."""
        v = self.values["pendulum.I"]
        if not math.isnan(v):
            return v
        mc, ms = self.values["pendulum.m_cam"], self.values["pendulum.m_shaft"]
        ls, lc = self.values["pendulum.L_shaft"], self.values["pendulum.L_cam"]
        return mc * (lc / 2 + ls) ** 2 + ms * ls**2 / 12

    @property
    def I_cm(self) -> float:  # noqa: N802
        """Inertia about the centre of mass (kg m^2), the same as :attr:`I`."""
        return self.I

    @property
    def I_pivot(self) -> float:  # noqa: N802
        """Inertia about the pivot, ``I_cm + m L^2`` (kg m^2): the ``J`` of the equations."""
        return self.I + self.m * self.L**2

    @property
    def physical(self) -> dict[str, float]:
        """The parameters of the equations of motion: M, m, L, I, b, g."""
        return {"M": self.M, "m": self.m, "L": self.L, "I": self.I, "b": self.b, "g": self.g}

    @property
    def realism(self) -> dict[str, float]:
        """The plant-realism values by bare name (``coulomb, stiction, backlash, deadband, duty_min,
        pot_inl, pot_inl_cycles``)."""
        return {k.split(".", 1)[1]: self.values[k] for k in REALISM_KEYS}

    @property
    def ideal(self) -> bool:
        """True when no plant-realism effect is on (the report's ideal robot)."""
        v = self.values
        return all(v[k] == 0.0 for k in REALISM_KEYS if k != "sensors.pot_inl_cycles")

    def replace(self, **changes: float) -> "RobotParams":
        """Return a copy with some values changed (keys dotted or bare), re-validated."""
        vals = dict(self.values)
        for k, v in changes.items():
            dotted = k if "." in k else next((d for d in SCHEMA if d.split(".", 1)[1] == k), k)
            if dotted not in SCHEMA:
                raise ParamError(k, "unknown parameter")
            vals[dotted] = v
        return params_from_dict(_nest(vals), source=self.source)


def _nest(flat: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for k, v in flat.items():
        sec, key = k.split(".", 1)
        out.setdefault(sec, {})[key] = v
    return out


def params_from_dict(data: Mapping[str, Any], source: str = "<dict>") -> RobotParams:
    """Validate a nested mapping ``{section: {key: value}}`` into :class:`RobotParams`.

    Raises
    ------
    ParamError
        On an unknown section or key, a missing required key, or a value out of range.
    """
    data, missing = _robot_file.normalise(data, ParamError)  # the minimal form, optional sections, I_cm/I_pivot
    sections = {k.split(".", 1)[0] for k in SCHEMA}
    values: dict[str, float] = {}
    for sec, body in data.items():
        if sec not in sections:
            raise ParamError(sec, f"unknown section (expected one of {sorted(sections)})")
        if not isinstance(body, Mapping):
            raise ParamError(sec, "expected a table of parameters")
        for key, value in body.items():
            dotted = f"{sec}.{key}"
            if dotted not in SCHEMA:
                raise ParamError(dotted, "unknown parameter")
            if isinstance(value, float) and math.isnan(value) and SCHEMA[dotted].default is not None:
                values[dotted] = value  # "derive it" marker, as produced by replace()
                continue
            values[dotted] = _check(dotted, value, SCHEMA[dotted])
    for dotted, spec in SCHEMA.items():
        if dotted not in values:
            if spec.default is None:
                raise ParamError(dotted, f"missing ({spec.doc}, {spec.unit})")
            values[dotted] = spec.default
    if values["sensors.pot_offset"] >= 2 ** values["sensors.adc_bits"]:
        raise ParamError("sensors.pot_offset", "must be below the ADC full scale 2**adc_bits")
    ticks = values["sensors.delay"] * values["loop.rate"]
    if abs(ticks - round(ticks)) > 1e-6:
        raise ParamError("sensors.delay", f"must be a whole number of control ticks of {1e3 / values['loop.rate']:g} ms "
                                          f"(loop.rate {values['loop.rate']:g} Hz), got {values['sensors.delay']!r} s "
                                          f"= {ticks:.4g} ticks")
    return RobotParams(values=_robot_file.guard(values, missing, source, ParamError), source=source)


def load_params(path: str | Path | None = None) -> RobotParams:
    """Load and validate a robot parameter file (default: the report's robot).

    Parameters
    ----------
    path : str or Path, optional
        TOML file; ``None`` loads ``sim/robot.toml``.

    Returns
    -------
    RobotParams

    Raises
    ------
    ParamError
        If the file cannot be read or parsed, or a key is missing, unknown or out of range.
    """
    p = Path(path) if path is not None else DEFAULT_PATH
    data = read_toml(p, "parameter file", lambda msg: ParamError("", msg))
    _robot_file.note_old_keys(data, str(p))
    return params_from_dict(data, source=str(p))


def read_toml(path: str | Path, what: str, error: Callable[[str], Exception]) -> dict[str, Any]:
    """The parsed TOML file ``path``, every failure one line: ``error(message)`` is raised.

    The one reader of the house's TOML inputs (robot files, uncertainty sets, sweep ranges);
    ``what`` names the file's kind in the message (``"parameter file"``).
    """
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise error(f"cannot read {what} {p}: {exc.strerror or exc}") from exc
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{p}: not valid TOML: {exc}") from exc


_DESIGN_ONLY = ("loop.track", "loop.a_max", "loop.phi_max", "loop.t_settle")
"""Keys of a plant file that are requirements, not physics: the design's values are used."""


def plant_params(design: RobotParams, plant: RobotParams) -> tuple[RobotParams, list[str]]:
    """The simulated robot of a ``--plant`` file, checked against the design it runs under.

    The plant file is a complete robot TOML.  Its physics (cart, pendulum, motor, sensors,
    ``sensors.delay``) is what gets simulated; ``loop.rate`` is the firmware's and must equal
    the design's; the constraints and the track (``loop.track``, ``loop.a_max``,
    ``loop.phi_max``, ``loop.t_settle``) are requirements, taken from the design.

    Returns
    -------
    (RobotParams, list of str)
        The plant, and one note per constraint key whose plant-file value was replaced by
        the design's (for the caller to print).

    Raises
    ------
    ParamError
        ``loop.rate`` differs from the design's.
    """
    if plant.values["loop.rate"] != design.values["loop.rate"]:
        raise ParamError("loop.rate", f"the plant file ({plant.source}) runs at {plant.values['loop.rate']:g} Hz but "
                                      f"the design ({design.source}) at {design.values['loop.rate']:g} Hz: the loop "
                                      f"rate is the firmware's, the plant file must give the same")
    notes, changes = [], {}
    for k in _DESIGN_ONLY:
        if plant.values[k] != design.values[k]:
            notes.append(f"{k}: the plant file's {plant.values[k]:g} ignored, the design's {design.values[k]:g} "
                         f"applies (a constraint, not physics)")
            changes[k] = design.values[k]
    out = plant.replace(**changes) if changes else plant
    return out, notes
