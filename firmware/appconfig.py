# App(config=...): every key in one table with its default and its valid range, read only
# through cfg_value() (App.__init__ and its parts' constructors: start-up only).
#
#   CONFIG rows (key, default, lo, hi): lo..hi inclusive; a default None means "the table's"
#   (deadband) or "see App.__init__" (epoch, reset_cause_boot); lo None: checked elsewhere
#   (emitter.check).  A config may also name a msgtable PARAMS entry: it overrides that
#   parameter's default (App.params).  The parameters that change the drive or the sensors
#   (msgtable.DRIVE_PARAMS: signs, pot offset, max_duty, node_id: a bad one tips the robot)
#   are checked against their PARAMS range; the others are not, so watchdog_ms=0 switches the
#   watchdog off (bench/tests only).
#   stall_ms/stall_duty: the no-motion check (F_STALL), on by default: STALL_MS at |duty| >=
#   STALL_DUTY beyond the table's deadband compensation; stall_ms=0: off.
# Nothing runs at import.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from . import msgtable as T

STALL_MS = const(100)  # no-motion check (F_STALL) default: this long without a count
STALL_DUTY = const(800)  # ... at |duty| at least this
_I16 = const(32767)
_TICKS_MASK = const(0x3FFFFFFF)  # tick/uptime counters wrap to 0 after this (fixmath)
WDT_MAX_MS = const(8388)  # the RP2040's longest hardware watchdog timeout
CONFIG = (
    ("emitter", "bytecode", None, None),  # how the hot parts are compiled (firmware/emitter.py)
    ("deadband", None, 0, _I16),  # duty counts added in the force's direction
    ("backemf", True, 0, 1),  # back-EMF compensation on
    ("boot", 0, 0, 255),  # boot counter (firmware/boot.py: mod 256)
    ("uptime_ms", 0, 0, _TICKS_MASK),  # board time at this start (main.py)
    ("wdt_ms", 0, 0, WDT_MAX_MS),  # hardware watchdog timeout, 0: none
    ("reset_cause", T.RC_POWER_ON, T.RC_POWER_ON, T.RC_EXCEPTION),  # what main.py found at boot
    ("reset_cause_boot", None, T.RC_POWER_ON, T.RC_EXCEPTION),  # VERSION.reset_cause after a MODE switch
    ("deadline", True, 0, 1),  # False: late ticks counted, never F_DEADLINE
    ("epoch", None, 0, _TICKS_MASK),  # a fixed first arming token (tests)
    ("seed", 0, 0, _TICKS_MASK),  # mixed into the first arming token (firmware/session.py)
    ("starts", 1, 1, _TICKS_MASK),  # loop starts since the board started (main.py)
    ("vsup_nom_mv", 12000, 1, 100000),  # the supply the table's motor constants assume
    ("vsup_min_mv", 0, 0, 100000),  # undervoltage threshold (F_UNDERVOLT), 0: none
    ("stall_ms", STALL_MS, 0, 60000),  # no-motion check (F_STALL) time, 0: off
    ("stall_duty", STALL_DUTY, 0, _I16),  # ... at |duty| at least this beyond the deadband compensation
)


def _check(key, v, lo, hi):
    if not isinstance(v, (int, bool)) or v < lo or v > hi:  # MicroPython: a bool is no int
        raise ValueError("config %s: %r is outside %d..%d" % (key, v, lo, hi))
    return v


def cfg_value(cfg, key):
    # config key's value (its CONFIG default when absent); outside the range, or a key
    # CONFIG lacks: a one-line ValueError naming the key.  Start-up only (a linear search)
    for k, d, lo, hi in CONFIG:
        if k == key:
            if key not in cfg:
                return d
            v = cfg[key]
            if lo is None or (v is None and d is None):
                return v
            return _check(key, v, lo, hi)
    raise ValueError("config %s: unknown key (none of App CONFIG or msgtable PARAMS)" % (key,))


def _param(key):
    for p in T.PARAMS:
        if p[1] == key:
            return p
    return None


def cfg_check(cfg):
    # every key of a config: a CONFIG key in its range, or a msgtable PARAMS name (a
    # DRIVE_PARAMS one in its PARAMS range)
    for key in cfg:
        p = _param(key)
        if p is None:
            cfg_value(cfg, key)
        elif p[0] in T.DRIVE_PARAMS:
            _check(key, cfg[key], p[3], p[4])


def cfg_params(cfg, params):
    # the parameters: msgtable's defaults, then the config's overrides by name
    for p in T.PARAMS:
        params[p[0]] = cfg[p[1]] if p[1] in cfg else p[5]


def epoch0(cfg, boot):
    # the arming token a start begins with (30 bits): os.urandom where the port has it, mixed
    # with config "seed" (main.py: firmware/session.py, which also mixes the RP2040's ring
    # oscillator and a seed persisted across starts -- an emulated board's urandom is the
    # same at every power-up) and the boot counter; config "epoch" fixes it (tests)
    e = cfg_value(cfg, "epoch")
    if e is not None:
        return e & _TICKS_MASK
    v = (cfg_value(cfg, "seed") ^ (boot << 22)) & _TICKS_MASK
    try:
        import os
        b = os.urandom(4)
        v ^= ((b[0] & 0x3F) << 24) | (b[1] << 16) | (b[2] << 8) | b[3]
    except (ImportError, AttributeError, OSError):
        pass
    return v & _TICKS_MASK
