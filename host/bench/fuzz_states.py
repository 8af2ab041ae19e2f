"""Command-sequence fuzz of the firmware app (issue 13 item 10): a hypothesis state machine.

:class:`FirmwareStates` drives the real :class:`firmware.app.App` under CPython (fast) with a
stand-in HAL, through the real command dispatcher (``firmware/commands.py``, payloads packed as
the link delivers them):

* boots: a good table, a flashed table failing its CRC or its check, a corrupt saved
  configuration (F_CONFIG), a restart after a watchdog or exception reset (F_RESET);
* commands: arm with the current or a stale epoch, disarm, clear_faults, param_set (any index,
  any value, loop_rate_hz included), gain uploads (good, failing the table check, wrong CRC),
  set_reference, host heartbeat, save_config;
* sensor faults: the angle ADC at a rail, tilted, noisy; encoder jumps and a stuck encoder; an
  open wiper (HAL ``adc_open``); motor supply undervoltage; the e-stop input;
* link and timing faults: silence (no host heartbeat: the link watchdog), late ticks and long gaps
  (the deadline rule, fed to the app exactly as ``App.run`` does every tick: ``_period(gap)`` then
  ``step()``, a queued save serviced between ticks).

Checked on every motor/enable write and after every tick: a non-zero duty only while the state is
BALANCING with no fault flag latched; the driver enable high only while BALANCING.  And after
every command: a stale arm changes nothing, a board whose table is not ready (or whose saved
configuration was corrupt) never arms, ``loop_rate_hz`` cannot be written, a present e-stop /
open wiper / railed ADC is latched by the next tick.

``make test`` runs a short version (tests/test_firmware_fuzz_states.py); ``make fuzz`` runs
:func:`bench` (>= 10^6 ticks, ``python -m host.bench.main --only fuzz_states``).
"""

from __future__ import annotations

import time
from typing import Any

from hypothesis import HealthCheck, Phase, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, rule, run_state_machine_as_test

from firmware import codec, commands, crc16
from firmware import gains as G
from firmware import msgtable as T
from firmware import supervisor as S
from firmware.app import App
from firmware.hal_base import Hal as HalBase
from firmware.crc32 import of as crc32_of, seal
from firmware.store import CORRUPT

__all__ = ["FirmwareStates", "STATS", "run", "bench"]

# what every run of the machine did (ticks by state, faults seen, commands accepted)
STATS: dict[str, int] = {}


def _count(key: str, n: int = 1) -> None:
    STATS[key] = STATS.get(key, 0) + n


class SafetyViolation(AssertionError):
    """The motor could run (duty or enable) outside BALANCING-with-no-fault."""


class FuzzHal(HalBase):
    """Stand-in board: sensors set by the machine, every motor/enable write checked at once."""

    # not host.boards.fwharness.StandInHal: this one checks every duty/enable write against the
    # supervisor's state as it happens, and offers the supply, e-stop and open-wiper inputs

    def __init__(self) -> None:
        self.adc = 2048
        self.enc = 0
        self.duty = 0
        self.en = 0
        self.t = 0
        self.supply_mv = 12000
        self.adc_open = False
        self.estop_low = False
        self.app: App | None = None

    def read_angle_raw(self) -> int:
        return self.adc

    def read_encoder(self) -> int:
        return self.enc

    def ticks_us(self) -> int:
        self.t = (self.t + 250) & 0x3FFFFFFF
        return self.t

    def read_supply_mv(self) -> int:
        return self.supply_mv

    def estop(self) -> bool:
        return self.estop_low

    def set_motor(self, duty: int) -> None:
        self.duty = duty
        a = self.app
        if duty != 0 and a is not None and (a.sup.state != S.BALANCING or a.sup.faults):
            raise SafetyViolation(f"duty {duty} written in state {a.sup.state} with faults {a.sup.faults:#x}")

    def set_enable(self, on: int) -> None:
        self.en = on
        a = self.app
        if on and a is not None and a.sup.state != S.BALANCING:
            raise SafetyViolation(f"enable high written in state {a.sup.state}")


class _Tx:
    """Dispatcher sender stand-in: the last reply (reason 0 for ACK)."""

    def __init__(self) -> None:
        self.reason = -1

    def send(self, mid: int, seq: int, vals, voff: int) -> None:
        if mid == T.ACK:
            self.reason = 0
        elif mid == T.NACK:
            self.reason = vals[voff + 1]


class _Store:
    """A configuration store stand-in: load() finds what the boot asked for; saves are kept."""

    def __init__(self, status: int) -> None:
        self.status = status
        self.n_params = 0
        self.n_table = 0
        self.saved = 0

    def load(self, check=None, migrate=None, params_ok=None):
        return self.status, None, None

    def save(self, params, table) -> int:
        self.saved += 1
        return self.saved


LAYOUT = codec.Layout()
CRCT = crc16.make_table()


def _table_bytes(flat) -> bytes:
    return b"".join(int(v).to_bytes(4, "little", signed=True) for v in flat)


GOOD = _table_bytes(G.FLAT)
_BAD_FLAT = list(G.FLAT)
_BAD_FLAT[0] += 1  # header version: fails the firmware's table check
BAD = _table_bytes(_BAD_FLAT)


class _Gains:
    def __init__(self, flat, crc) -> None:
        self.LAYOUT, self.FLAT, self.VERSION, self.CRC = G.LAYOUT, flat, G.VERSION, crc


BOOTS = ("good", "good", "good", "bad_crc", "bad_shape", "corrupt_config", "watchdog_reset", "exception_reset")

# parameter values worth trying: each parameter's edges and default, and anything in between
_PARAM = st.one_of(
    st.tuples(st.integers(0, T.N_PARAMS - 1), st.sampled_from(("min", "max", "default", "mid"))),
    st.tuples(st.integers(0, T.N_PARAMS + 2), st.integers(-(2**30) + 1, 2**30 - 1)),
)


class FirmwareStates(RuleBasedStateMachine):
    """The app, its dispatcher and a stand-in HAL under random commands and faults."""

    def __init__(self) -> None:
        super().__init__()
        self.app: App | None = None

    # ---- boot ----
    @initialize(boot=st.sampled_from(BOOTS), epoch=st.integers(0, 255), tilt=st.integers(-30, 30))
    def boot(self, boot: str, epoch: int, tilt: int) -> None:
        hal = FuzzHal()
        cfg: dict[str, Any] = {"epoch": epoch, "vsup_nom_mv": 12000, "vsup_min_mv": 9000}
        gains = None
        if boot == "bad_crc":
            gains = _Gains(G.FLAT, G.CRC ^ 1)
        elif boot == "bad_shape":
            gains = _Gains(tuple(_BAD_FLAT), G.CRC)
        elif boot == "watchdog_reset":
            cfg["reset_cause"] = T.RC_WATCHDOG
        elif boot == "exception_reset":
            cfg["reset_cause"] = T.RC_EXCEPTION
        app = App(hal, gains=gains, config=cfg)
        if boot == "corrupt_config":
            app.attach_store(_Store(CORRUPT))
        else:
            app.attach_store(_Store(1))  # EMPTY: first start, defaults
        hal.app = app
        self.hal, self.app, self.tx = hal, app, _Tx()
        self.disp = commands.Dispatcher(app, LAYOUT, self.tx, CRCT)
        self.ready = boot not in ("bad_crc", "bad_shape")  # the table may run
        self.config_bad = boot == "corrupt_config"
        self.rate = app.rate
        self.offset = app.sensors.pot_offset
        hal.adc = self.offset + tilt
        self.moving = True  # the encoder follows the duty (False: stuck)
        # App.run: the period is measured before balancing
        app.sup.timing_ok = False
        self.period = app.period_us
        _count("boots")
        _count("boot_" + boot)

    # ---- plumbing ----
    def _cmd(self, mid: int, *vals: int, data: bytes | None = None) -> int:
        buf = bytearray(16)
        v = list(vals) + [0] * 4
        seal(LAYOUT, mid, v, 0, buf, 2)  # the integrity check of a command that moves the cart
        LAYOUT.pack(mid, v, 0, buf, 2)
        if data is not None:
            buf[4:4 + len(data)] = data
        r = self.disp.handle(mid, 1, buf, 2)
        _count("cmd_ok" if r == T.OK else "cmd_refused")
        self._check(model=False)
        return r

    def _tick(self, gap: int | None = None, feed: bool = False) -> None:
        app, hal = self.app, self.hal
        # App.run's per-tick body: the measured gap, the step, a queued save between ticks
        app._period(self.period if gap is None else gap)
        if feed:
            self._cmd(T.HOST_HEARTBEAT)
        app.step()
        if app.save_seq >= 0:
            app.service_save()
        if self.moving and hal.duty:
            hal.enc = (hal.enc + (1 if hal.duty > 0 else -1)) & 0xFFFF
        st_ = app.sup.state
        _count("ticks")
        _count(("tick_disarmed", "tick_armed", "tick_balancing", "tick_fault")[st_])
        if hal.duty:
            _count("tick_duty")
        self._check()
        sup = app.sup
        if hal.estop_low:
            assert sup.faults & S.F_ESTOP and st_ == S.FAULT
        if hal.adc_open:
            assert sup.faults & S.F_ADC_OPEN and st_ == S.FAULT
        if hal.adc <= 0 or hal.adc >= 4095:
            assert sup.faults & S.F_ADC_RAIL and st_ == S.FAULT
        if not self.ready:
            assert sup.faults & S.F_GAINS and st_ == S.FAULT
        if sup.faults:
            for bit, name, _d in T.FAULTS:
                if sup.faults & bit:
                    _count("fault_" + name)

    def _check(self, model: bool = True) -> None:
        app, hal = self.app, self.hal
        st_ = app.sup.state
        if hal.duty != 0 and (st_ != S.BALANCING or app.sup.faults):
            raise SafetyViolation(f"duty {hal.duty} in state {st_} with faults {app.sup.faults:#x}")
        if hal.en and st_ != S.BALANCING:
            raise SafetyViolation(f"enable high in state {st_}")
        if st_ == S.BALANCING:
            assert app.sup.faults == 0
        if not app.sup.ready or app.config_bad:
            assert st_ not in (S.ARMED, S.BALANCING), "a board that is not ready is armed"
        if not model:
            return
        if not self.ready or self.config_bad:
            assert st_ not in (S.ARMED, S.BALANCING), "a board that is not ready is armed"
        assert app.sup.ready == self.ready and app.config_bad == self.config_bad
        assert app.rate == self.rate and app.period_us == self.period

    @invariant()
    def safe(self) -> None:
        if self.app is not None:
            self._check()

    # ---- time ----
    @rule(n=st.integers(1, 80), feed=st.booleans(), late=st.sampled_from((0, 0, 0, 1, 2)))
    def run_ticks(self, n: int, feed: bool, late: int) -> None:
        # late 1: every 7th tick 3 periods late; 2: one gap of 12 periods first
        for k in range(n):
            gap = None
            if late == 1 and k % 7 == 3:
                gap = 3 * self.period
            elif late == 2 and k == 0:
                gap = 12 * self.period
            self._tick(gap, feed)

    @rule(n=st.integers(100, 300))
    def silence(self, n: int) -> None:
        # the host stops talking: the link watchdog (watchdog_ms) must cut an armed board
        wd = self.app.sup.wd_ticks
        armed_through = True
        for _ in range(n):
            before = self.app.sup.state
            self._tick()
            if before not in (S.ARMED, S.BALANCING):
                armed_through = False
        if armed_through and 0 < wd < n:
            assert self.app.sup.faults & S.F_WATCHDOG

    # ---- commands ----
    @rule(stale=st.booleans(), delta=st.integers(1, 255))
    def arm(self, stale: bool, delta: int) -> None:
        app = self.app
        before = app.sup.state
        ep = (app.epoch + delta) & 0x3FFFFFFF if stale else app.epoch
        r = self._cmd(T.ARM, ep)
        if stale:
            assert r in (T.R_STALE_EPOCH, T.R_FAULTED), r
            assert app.sup.state == before
        elif r == T.OK:
            _count("arm_accepted")
            assert self.ready and not self.config_bad
            assert app.sup.state in (S.ARMED, S.BALANCING)
        if not self.ready and before == S.DISARMED and not stale:
            assert r == T.R_NOT_READY, r

    @rule()
    def disarm(self) -> None:
        assert self._cmd(T.DISARM) == T.OK
        assert self.hal.duty == 0 and not self.hal.en
        assert self.app.sup.state in (S.DISARMED, S.FAULT)

    @rule()
    def clear(self) -> None:
        self._cmd(T.CLEAR_FAULTS)

    @rule(p=_PARAM)
    def param_set(self, p) -> None:
        i, v = p
        if isinstance(v, str):
            q = T.PARAMS[i]
            v = {"min": q[3], "max": q[4], "default": q[5], "mid": (q[3] + q[4]) // 2}[v]
        r = self._cmd(T.PARAM_SET, i, v)
        if i == T.P_LOOP_RATE:
            assert r in (T.R_READ_ONLY, T.R_OUT_OF_RANGE), r
        elif i >= T.N_PARAMS:
            assert r == T.R_BAD_INDEX
        assert self.app.param_get(T.P_LOOP_RATE) == self.rate

    @rule(kind=st.sampled_from(("good", "bad", "bad_crc", "short")))
    def upload(self, kind: str) -> None:
        data = BAD if kind == "bad" else GOOD
        crc = crc16.compute(CRCT, data, 0, len(data))
        if kind == "bad_crc":
            crc ^= 0x0100
        n = len(data) - (6 if kind == "short" else 0)
        motor_off = self.app.sup.state in (S.DISARMED, S.FAULT)
        if self._cmd(T.GAINS_BEGIN, n, crc, self.app.epoch) != T.OK:
            return
        for off in range(0, n, 6):
            chunk = data[off:min(off + 6, n)]
            if self._cmd(T.GAINS_CHUNK, off, data=chunk) != T.OK:
                return
        r = self._cmd(T.GAINS_COMMIT, crc32_of(data, n))
        if kind == "good" and motor_off:
            assert r == T.OK, r
            self.ready = True
            self.config_bad = False
            _count("upload_good")
        else:
            assert r != T.OK, (kind, r)

    @rule(x_um=st.one_of(st.integers(-800000, 800000), st.integers(-(2**30) + 1, 2**30 - 1)))
    def reference(self, x_um: int) -> None:
        self._cmd(T.SET_REFERENCE, x_um)

    @rule()
    def host_heartbeat(self) -> None:
        self._cmd(T.HOST_HEARTBEAT)

    @rule()
    def save(self) -> None:
        self._cmd(T.SAVE_CONFIG)

    @rule(n=st.integers(20, 200), tilt=st.integers(-20, 20))
    def operate(self, n: int, tilt: int) -> None:
        # an operator's recovery: sensors healthy, clear, arm with the epoch just read, run
        # with the host feeding the link watchdog (reaches BALANCING whenever the board may)
        hal = self.hal
        hal.estop_low = False
        hal.adc_open = False
        hal.supply_mv = 12000
        self.moving = True
        self.offset = self.app.sensors.pot_offset
        hal.adc = self.offset + tilt
        self._cmd(T.CLEAR_FAULTS)
        r = self._cmd(T.ARM, self.app.epoch)
        if r == T.OK:
            _count("arm_accepted")
        for _ in range(n):
            self._tick(feed=True)

    # ---- sensors ----
    @rule(kind=st.sampled_from(("upright", "near", "near", "near", "tilted", "rail0", "rail_full", "any")), v=st.integers(0, 4095))
    def angle(self, kind: str, v: int) -> None:
        o = self.offset = self.app.sensors.pot_offset
        self.hal.adc = {"upright": o, "near": o + (v % 41) - 20, "tilted": o + 300 + (v % 200),
                        "rail0": 0, "rail_full": 4095, "any": v}[kind]

    @rule(step=st.one_of(st.integers(-20, 20), st.integers(-20, 20), st.integers(-3000, 3000)))
    def encoder(self, step: int) -> None:
        # small moves, and jumps beyond what the cart can move in a tick
        self.hal.enc = (self.hal.enc + step) & 0xFFFF

    @rule(moving=st.booleans())
    def encoder_stuck(self, moving: bool) -> None:
        self.moving = moving

    @rule(on=st.sampled_from((False, False, False, True)))
    def open_wiper(self, on: bool) -> None:
        self.hal.adc_open = on

    @rule(mv=st.sampled_from((12000, 12000, 11000, 9500, 8500, 6000, 14000)))
    def supply(self, mv: int) -> None:
        self.hal.supply_mv = mv

    @rule(low=st.sampled_from((False, False, False, True)))
    def estop(self, low: bool) -> None:
        self.hal.estop_low = low


def run(max_examples: int, steps: int = 50, shrink: bool = True, derandomize: bool = False) -> None:
    """Run the machine (hypothesis drives it); raises on a violation, shrunk to a short sequence.

    ``derandomize=True`` draws the same sequences on every run (the short test in ``make test``: a
    random draw of 40 examples misses one fault kind about one run in three); ``make fuzz`` draws
    new ones each time.
    """
    s = settings(max_examples=max_examples, stateful_step_count=steps, deadline=None, database=None,
                 suppress_health_check=list(HealthCheck), derandomize=derandomize,
                 phases=[Phase.generate, Phase.shrink] if shrink else [Phase.generate])
    run_state_machine_as_test(FirmwareStates, settings=s)


def bench(min_ticks: int = 1_000_000) -> dict[str, Any]:
    """``make fuzz``: the state machine until at least ``min_ticks`` control ticks ran."""
    STATS.clear()
    t0 = time.perf_counter()
    rounds = 0
    while STATS.get("ticks", 0) < min_ticks:
        run(max_examples=200, steps=100)
        rounds += 1
    wall = time.perf_counter() - t0
    ticks = STATS.get("ticks", 0)
    rows = [{"ticks": ticks, "ticks_per_s": ticks / wall, "boots": STATS.get("boots", 0),
             "commands_ok": STATS.get("cmd_ok", 0), "commands_refused": STATS.get("cmd_refused", 0),
             "arms_accepted": STATS.get("arm_accepted", 0), "good_uploads": STATS.get("upload_good", 0),
             "violations": 0}]
    by_state = {k[5:]: v for k, v in STATS.items() if k.startswith("tick_")}
    faults = {k[6:]: v for k, v in STATS.items() if k.startswith("fault_")}
    boots = {k[5:]: v for k, v in STATS.items() if k.startswith("boot_")}
    notes = [
        f"{ticks} ticks of firmware.app.App (CPython) in {wall:.1f} s, {rounds} rounds of 200 examples x 100 steps",
        "ticks by state: " + ", ".join(f"{k} {v}" for k, v in sorted(by_state.items())),
        "ticks with a latched flag: " + ", ".join(f"{k} {v}" for k, v in sorted(faults.items())),
        "boots: " + ", ".join(f"{k} {v}" for k, v in sorted(boots.items())),
        "checked on every motor/enable write and after every tick and command: duty != 0 only while "
        "BALANCING with no fault flag, enable high only while BALANCING; violations: 0",
    ]
    return {"title": "Firmware command-sequence fuzz (hypothesis state machine, >= 1e6 ticks, CPython)",
            "rows": rows, "notes": notes, "stats": dict(STATS)}


if __name__ == "__main__":
    import json
    import sys

    n = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
    print(json.dumps(bench(n), indent=2, default=float))
