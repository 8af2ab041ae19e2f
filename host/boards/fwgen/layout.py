"""The per-tick state layout of the firmware's viper builds, declared once as data.

``Controller.step`` keeps its state in the controller's int32 arrays and int attributes
(:data:`CONTROLLER_ARRAYS`, :data:`CONTROLLER_SCALARS`); the viper build reads the arrays
through ``ptr32``.  ``Sensors``, ``Supervisor``, ``Motor`` and ``Timing`` keep their per-tick
attributes, in the viper build, as slots of one ``array('i')`` per object (:data:`TICK_PARTS`):
an attribute load there costs ~2.5 us on a 125 MHz M0+, a ptr32 load a few cycles.  The
generated classes (``SensorsV`` …) show the same attribute names to the cold paths through
properties (the named accessors), and their per-tick methods call the generated viper
functions on the slot array.  Slot kinds: ``"i"`` signed (loads sign-extended: a 64-bit
port's ptr32 load is zero-extended), ``"u"`` never negative, ``"b"`` a flag (bool, 0/1).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from host.boards.fwgen.viper import SlotObject

__all__ = ["FIRMWARE", "CONTROLLER_ARRAYS", "CONTROLLER_SCALARS", "TickPart", "TICK_PARTS", "TICKS_DIFF", "PACER",
           "SUPPLY", "STEP"]

FIRMWARE = Path(__file__).resolve().parents[3] / "firmware"

# Controller.step: the int32 arrays (ptr32 locals in viper) and the int attributes it reads
CONTROLLER_ARRAYS = ("p", "m", "lim", "sm", "rf", "xf", "kf", "kv", "b", "kb", "kvb", "ad", "bd", "sa", "ra")
CONTROLLER_SCALARS = ("kr", "hk", "hkv", "d", "ki", "sk", "ulim", "uhi", "ulo", "ilim", "skv", "aw", "integ", "est")

# fixmath.ticks_diff written out (a call costs more than this on a board): the same values for
# a clock whose period is a multiple of 2**30
TICKS_DIFF = "out = (a0 - a1) & _TICKS_MASK\nif out >= _TICKS_HALF:\n    out |= _TICKS_HIGH\n"


@dataclass(frozen=True)
class TickPart:
    """One plain class whose per-tick methods get a viper build on a slot array.

    Attributes
    ----------
    module : str
        The firmware module holding the class (``"sensors"``).
    cls : str
        The plain class (``"Sensors"``); the generated one is ``cls + "V"``.
    state : SlotObject
        Its slot layout.
    methods : tuple of (str, str)
        Method name -> generated viper function name.
    inline : tuple of (str, str)
        ``self.<name>(...)`` calls expanded from a template (see :mod:`host.boards.fwgen.viper`).
    """

    module: str
    cls: str
    state: SlotObject
    methods: tuple[tuple[str, str], ...]
    inline: tuple[tuple[str, str], ...] = ()


TICK_PARTS: tuple[TickPart, ...] = (
    TickPart("sensors", "Sensors", SlotObject("SN", (
        ("adc_max", "i"), ("pot_offset", "i"), ("adc_sign", "i"), ("counts", "i"), ("ylp", "i"), ("yp", "i"),
        ("qp", "u"), ("primed", "b"), ("last", "u"), ("enc_sign", "i"), ("delta", "i"), ("encj", "i"),
        ("jump", "b"), ("pos", "i"), ("ylx", "i"), ("yx", "i"), ("qx", "u"), ("rail", "b"), ("play", "i"),
        ("wpos", "i"))),
        (("update", "sensors_update"),)),
    # timing_ok stays an attribute: App.run reads it every tick, the update only when ARMED
    TickPart("supervisor", "Supervisor", SlotObject("SU", (
        ("state", "u"), ("faults", "u"), ("last", "u"), ("tilt_counts", "i"), ("arm_counts", "i"),
        ("track_counts", "i"), ("wd_ticks", "i"), ("wd_count", "u"), ("stall_ticks", "i"), ("stall_duty", "i"),
        ("stall_count", "u"), ("ready", "b"))),
        (("update", "supervisor_update"),)),
    TickPart("motor", "Motor", SlotObject("MO", (
        ("backemf", "b"), ("max_duty", "i"), ("vscale", "i"), ("kdu", "i"), ("kdv", "i"), ("sd", "u"),
        ("half", "i"), ("deadband", "i"))),
        (("duty", "motor_duty"),)),
    TickPart("timing", "Timing", SlotObject("TM", (
        ("period_us", "i"), ("mean_us", "i"), ("worst", "i"), ("misses", "i"), ("step_max", "i"),
        ("overruns", "u"), ("step_min", "i"), ("period_max", "i"), ("jitter_max", "i"), ("steps", "u"),
        ("_sum", "u"), ("_n", "u"), ("last_us", "u"), ("_have_last", "b"))),
        (("begin", "timing_begin"), ("end", "timing_end")),
        (("_diff", TICKS_DIFF),)),
)


# Pacer.tick (firmware/pacer.py) -> fasttick.PacerV.tick, a viper method: the ints it reads on
# itself and on the app, its parameter array (built only when the app has one: `p is not None`)
PACER = {"ints": {"self": ("seq", "_telem_left", "_hb_us"), "app": ("period_us",)},
         "arrays": {"self": ("_p",)}}
# App._supply (firmware/app.py) -> fasttick.SupplyV(app).update: the app's state through a helper
SUPPLY = {"ints": {"app": ("_vsup_acc", "vsup_mv", "vsup_min", "vsup_nom")}, "calls": {"app": ("_read_vsup",)},
          "self_as": "app"}

# App.step (firmware/app.py) -> fasttick.StepV.step (host/boards/fwgen/step.py): its parts with a
# slot layout (self.<attr> -> class of TICK_PARTS), the int attributes and int-returning methods
# it reads (by the object's path in the source), the controller's int32 array it indexes, and the
# conditions on what the HAL offers, fixed at App construction (bits of StepV.opts)
STEP = {
    "parts": {"timing": "Timing", "sensors": "Sensors", "sup": "Supervisor", "motor": "Motor"},
    "ints": {"self": ("_frames", "_ext", "duty", "_st", "tick", "_us_frac", "period_us", "uptime_ms"),
             "self.hal": ("n_sensor",), "c": ("phi_on", "vh")},
    "calls": {"self": ("_read_adc", "_read_enc", "_supply", "_cstep", "_excite")},
    "int_locals": ("ticks",),  # locals bound to int-returning callables (ticks = self._ticks)
    "arrays": {"c": ("p",)},
    "fixed": ("self._has_frames", "self._estop is not None", "self._has_open", "self._read_vsup is not None"),
}
