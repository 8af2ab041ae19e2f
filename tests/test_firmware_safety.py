"""Issue 13 safety rules on the firmware app, under CPython and the MicroPython unix port.

One scenario script (plain Python that both interpreters run) plays every case on the real
``firmware.app.App`` with a stand-in HAL and prints named observations; each test checks one
rule, once per interpreter:

* the deadline rule (``App.run``): a step start more than 1.5 periods after the previous one is a
  late tick; each adds 25 to a score that each on-time tick lowers by 1; F_DEADLINE latches when
  the score passes 100 (the 5th late tick in a row, or about 1 late tick in 25 sustained) or on
  one gap longer than 10 periods -- only while armed/balancing; balancing starts only after 16
  on-time periods; ``deadline: False`` (desktop HIL) only counts;
* readiness: a table that failed its check or CRC refuses ``arm`` with ``not_ready`` after
  ``clear_faults`` and re-latches F_GAINS on the next tick; only a good upload makes it usable;
* ``param_set(loop_rate_hz)`` is refused ``read_only``; the period stays the table's RATE;
* F_RESET after a watchdog-cause or exception-cause boot, the cause in VERSION;
* ``firmware/main.py``'s exception path (unix port only: it needs ``sys.print_exception``):
  motor and enable off, F_LOOP in one last heartbeat, marker RC_EXCEPTION, board reset; Ctrl-C
  stops the watchdog and clears the marker.

Plus, in CPython only: the supervisor's F_* constants are exactly ``msgtable.FAULTS`` (names
and bits), and docs/firmware.md documents every flag.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import fwharness as H
from firmware import msgtable as T
from firmware import supervisor as S
from host.boards.mpyrun import run_unix
from host.link import messages as M

ROOT = Path(__file__).resolve().parents[1]

# ---- the scenario script (MicroPython and CPython) ----
COMMON = H.FAKE_HAL + """
from firmware.app import App
from firmware import msgtable as T
from firmware import supervisor as S
from firmware import gains as G
from firmware import codec, commands, crc16
from firmware.crc32 import seal, of as crc32_of

def chk(name, v):
    print('OBS ' + name + ' ' + str(int(v)))

StandIn = Hal

class Hal(StandIn):
    # fwharness.FAKE_HAL's stand-in board with slow steps, the enable pin and every duty checked
    # against the state: the clock advances `inc` us per read, `delay[n]` us more while the n-th
    # step reads the encoder (a slow step); every duty and enable recorded and checked
    def __init__(s):
        StandIn.__init__(s)
        s.en = 0
        s.inc = 10
        s.n = 0
        s.delay = {}
        s.app = None
        s.bad = 0
    def read_encoder(s):
        s.n += 1
        d = s.delay.get(s.n, 0)
        if d:
            s.t = (s.t + d) & 0x3FFFFFFF
        return s.enc
    def set_motor(s, d):
        StandIn.set_motor(s, d)
        a = s.app
        if d != 0 and a is not None and (a.sup.state != S.BALANCING or a.sup.faults):
            s.bad += 1
    def set_enable(s, on):
        s.en = on
        a = s.app
        if on and a is not None and a.sup.state != S.BALANCING:
            s.bad += 1

class Watch:
    # a link stand-in: run() polls it after every step; records the first step with a flag
    # and the first balancing step; arms the app at step `arm_at` (-1: never)
    def __init__(s, hal, app, flag, arm_at=-1):
        s.hal = hal
        s.app = app
        s.flag = flag
        s.arm_at = arm_at
        s.first = -1
        s.first_bal = -1
        s.fault_duty = -1
        s.fault_en = -1
        s.n_late = -1
    def poll(s):
        a = s.app
        if s.hal.n == s.arm_at:
            a.cmd_arm()
        if s.first < 0 and a.sup.faults & s.flag:
            s.first = s.hal.n
            s.fault_duty = s.hal.duty
            s.fault_en = s.hal.en
            s.n_late = a.n_late
        if s.first_bal < 0 and a.sup.state == S.BALANCING:
            s.first_bal = s.hal.n

def fresh(gains=None, **cfg):
    hal = Hal()
    cfg.setdefault('watchdog_ms', 0)
    cfg.setdefault('stall_ms', 0)
    cfg.setdefault('epoch', 7)
    app = App(hal, gains=gains, config=cfg)
    hal.app = app
    hal.adc = app.sensors.pot_offset
    return hal, app

class Tx:
    # dispatcher sender stand-in: the last reply (ACK: reason 0; NACK: its reason)
    def __init__(s):
        s.mid = -1
        s.reason = -1
    def send(s, mid, seq, vals, voff):
        if mid == T.ACK:
            s.mid = vals[voff]
            s.reason = 0
        elif mid == T.NACK:
            s.mid = vals[voff]
            s.reason = vals[voff + 1]

LAYOUT = codec.Layout()
CRCT = crc16.make_table()

def cmd(disp, mid, *vals):
    # one command through the dispatcher as the link would hand it; -> OK or the reason
    buf = bytearray(16)
    v = list(vals) + [0] * 4
    seal(LAYOUT, mid, v, 0, buf, 2)  # the integrity check of a command that moves the cart
    LAYOUT.pack(mid, v, 0, buf, 2)
    return disp.handle(mid, 1, buf, 2)

def table_bytes(flat):
    b = bytearray(4 * len(flat))
    for i in range(len(flat)):
        x = flat[i] & 0xFFFFFFFF
        b[4 * i] = x & 0xFF
        b[4 * i + 1] = (x >> 8) & 0xFF
        b[4 * i + 2] = (x >> 16) & 0xFF
        b[4 * i + 3] = (x >> 24) & 0xFF
    return b

def upload(disp, data, crc=None):
    # GAINS_BEGIN, chunks, GAINS_COMMIT; -> the commit's reason
    n = len(data)
    if crc is None:
        crc = crc16.compute(CRCT, data, 0, n)
    r = cmd(disp, T.GAINS_BEGIN, n, crc, disp.target.epoch)
    if r:
        return 100 + r
    for off in range(0, n, 6):
        buf = bytearray(16)
        LAYOUT.pack(T.GAINS_CHUNK, [off, 0], 0, buf, 2)
        for i in range(6):
            buf[4 + i] = data[off + i] if off + i < n else 0
        r = disp.handle(T.GAINS_CHUNK, 1, buf, 2)
        if r:
            return 200 + r
    return cmd(disp, T.GAINS_COMMIT, crc32_of(data))

class Gains:
    def __init__(s, flat, crc):
        s.LAYOUT = G.LAYOUT
        s.FLAT = flat
        s.VERSION = G.VERSION
        s.CRC = crc
"""

SCENARIOS = """
# ---------------- deadline rule ----------------
hal, app = fresh()
P = app.period_us
chk('period_us', P)
# warm-up: armed before the loop starts; step 1 has no period, steps 2..17 are on time
w = Watch(hal, app, S.F_DEADLINE)
app.set_link(w)
app.cmd_arm()
app.run(40, lock=False)
chk('warmup_first_balancing_step', w.first_bal)
chk('warmup_faults', app.sup.faults)

# k late ticks in a row while balancing (a slow step of 3 periods: the next start is late)
for k in (4, 5, 8):
    hal, app = fresh()
    w = Watch(hal, app, S.F_DEADLINE)
    app.set_link(w)
    app.cmd_arm()
    for j in range(k):
        hal.delay[30 + j] = 3 * P
    app.run(30 + k + 20, lock=False)
    chk('late%d_first_fault_step' % k, w.first)
    chk('late%d_fault_duty' % k, w.fault_duty)
    chk('late%d_fault_en' % k, w.fault_en)
    chk('late%d_n_late' % k, app.n_late)
    chk('late%d_state' % k, app.sup.state)
    chk('late%d_faults' % k, app.sup.faults)
    chk('late%d_bad' % k, hal.bad)

# sustained: one late tick every 26 (score stays bounded) vs every 25 (it climbs by 1 a cycle)
for every in (26, 25):
    hal, app = fresh()
    w = Watch(hal, app, S.F_DEADLINE)
    app.set_link(w)
    app.cmd_arm()
    for j in range(100):
        hal.delay[30 + every * j] = 3 * P
    app.run(30 + every * 99 + 5, lock=False)
    chk('every%d_first_fault_step' % every, w.first)
    chk('every%d_n_late_at_fault' % every, w.n_late)
    chk('every%d_state' % every, app.sup.state)

# one long gap while balancing: 9.5 periods passes, 10.5 periods latches at once
for name, d in (('gap9', 19 * P // 2), ('gap11', 21 * P // 2)):
    hal, app = fresh()
    w = Watch(hal, app, S.F_DEADLINE)
    app.set_link(w)
    app.cmd_arm()
    hal.delay[30] = d
    app.run(40, lock=False)
    chk(name + '_first_fault_step', w.first)
    chk(name + '_state', app.sup.state)
    chk(name + '_fault_duty', w.fault_duty)

# armed but not yet balancing (pendulum outside the arm window): the rule applies too
hal, app = fresh()
w = Watch(hal, app, S.F_DEADLINE)
app.set_link(w)
app.cmd_arm()
hal.adc = app.sensors.pot_offset + 400
for j in range(5):
    hal.delay[30 + j] = 3 * P
app.run(40, lock=False)
chk('armed_first_fault_step', w.first)
chk('armed_first_balancing_step', w.first_bal)

# disarmed: late ticks and a 20-period gap are counted, never a fault; arming afterwards
# waits for 16 on-time periods again
hal, app = fresh()
w = Watch(hal, app, S.F_DEADLINE)
app.set_link(w)
for j in range(10):
    hal.delay[20 + j] = 3 * P
hal.delay[40] = 20 * P
app.run(60, lock=False)
chk('disarmed_faults', app.sup.faults)
chk('disarmed_state', app.sup.state)
chk('disarmed_n_late', app.n_late)
chk('disarmed_timing_ok', app.sup.timing_ok)

hal, app = fresh()
a = Watch(hal, app, 0, arm_at=5)  # no flag watched: armed at step 5, the first balancing step
app.set_link(a)
hal.delay[50] = 3 * P
app.run(100, lock=False)
chk('rewarm_first_balancing_step', a.first_bal)
chk('rewarm_faults', app.sup.faults)

# deadline False (the unix-port HIL on a desktop OS): counted only
hal, app = fresh(deadline=False)
w = Watch(hal, app, S.F_DEADLINE)
app.set_link(w)
app.cmd_arm()
for j in range(20):
    hal.delay[30 + j] = 3 * P
hal.delay[60] = 20 * P
app.run(80, lock=False)
chk('nocheck_faults', app.sup.faults)
chk('nocheck_n_late', app.n_late)

# ---------------- readiness ----------------
for name, g in (('crc', Gains(G.FLAT, G.CRC ^ 1)), ('shape', None)):
    if g is None:
        f = list(G.FLAT)
        f[0] = f[0] + 1  # HDR version: fails validate() (and the CRC)
        g = Gains(tuple(f), G.CRC)
    hal, app = fresh(gains=g)
    tx = Tx()
    d = commands.Dispatcher(app, LAYOUT, tx)
    chk(name + '_boot_faults', app.sup.faults)
    chk(name + '_boot_state', app.sup.state)
    chk(name + '_boot_ready', app.sup.ready)
    chk(name + '_arm_faulted', cmd(d, T.ARM, app.epoch))
    chk(name + '_clear', cmd(d, T.CLEAR_FAULTS))
    chk(name + '_cleared_state', app.sup.state)
    chk(name + '_arm_not_ready', cmd(d, T.ARM, app.epoch))
    chk(name + '_arm_not_ready_state', app.sup.state)
    app.step()
    chk(name + '_relatched_faults', app.sup.faults)
    chk(name + '_relatched_state', app.sup.state)
    for k in range(5):
        cmd(d, T.CLEAR_FAULTS)
        cmd(d, T.ARM, app.epoch)
        for j in range(20):
            app.step()
    chk(name + '_loop_state', app.sup.state)
    chk(name + '_loop_duty_sets_nonzero', hal.bad)
    # a bad upload changes nothing; a good one makes the board usable
    bad = list(G.FLAT)
    bad[0] += 1
    chk(name + '_bad_upload', upload(d, table_bytes(bad)))
    chk(name + '_bad_upload_ready', app.sup.ready)
    chk(name + '_wrong_crc_upload', upload(d, table_bytes(G.FLAT), G.CRC ^ 0x100))
    chk(name + '_good_upload', upload(d, table_bytes(G.FLAT)))
    chk(name + '_good_upload_ready', app.sup.ready)
    chk(name + '_good_upload_crc', app.gains_crc == G.CRC)
    chk(name + '_good_upload_faults', app.sup.faults)
    chk(name + '_after_upload_clear', cmd(d, T.CLEAR_FAULTS))
    chk(name + '_after_upload_arm', cmd(d, T.ARM, app.epoch))
    for j in range(3):
        app.step()
    chk(name + '_after_upload_state', app.sup.state)

# a good board: a bad upload is refused and the live table stays
hal, app = fresh()
tx = Tx()
d = commands.Dispatcher(app, LAYOUT, tx)
bad = list(G.FLAT)
bad[0] += 1
chk('good_bad_upload', upload(d, table_bytes(bad)))
chk('good_bad_upload_ready', app.sup.ready)
chk('good_bad_upload_crc', app.gains_crc == G.CRC)
chk('good_bad_upload_faults', app.sup.faults)

# ---------------- loop_rate_hz is read-only ----------------
hal, app = fresh()
tx = Tx()
d = commands.Dispatcher(app, LAYOUT, tx)
rate = app.rate
for v in (250, 500, 1000):
    chk('rate_set_%d' % v, cmd(d, T.PARAM_SET, T.P_LOOP_RATE, v))
chk('rate_set_direct', app.param_set(T.P_LOOP_RATE, 250))
chk('rate_set_low', cmd(d, T.PARAM_SET, T.P_LOOP_RATE, 10))
chk('rate_after', app.param_get(T.P_LOOP_RATE) == rate)
chk('rate_period_after', app.period_us == 1000000 // rate)
chk('rate_timing_period', app.timing.period_us == 1000000 // rate)
chk('rate_other_param_ok', cmd(d, T.PARAM_SET, T.P_TILT_LIMIT, 400))
chk('rate_after_other', app.param_get(T.P_LOOP_RATE) == rate)

# ---------------- F_RESET after a watchdog/exception boot ----------------
for name, rc in (('power_on', T.RC_POWER_ON), ('watchdog', T.RC_WATCHDOG), ('exception', T.RC_EXCEPTION)):
    hal, app = fresh(reset_cause=rc)
    tx = Tx()
    d = commands.Dispatcher(app, LAYOUT, tx)
    arr = [0] * 8
    app.fill_version(arr)
    chk('rc_' + name + '_faults', app.sup.faults)
    chk('rc_' + name + '_state', app.sup.state)
    chk('rc_' + name + '_version_cause', arr[4])
    chk('rc_' + name + '_arm', cmd(d, T.ARM, app.epoch))
    cmd(d, T.CLEAR_FAULTS)
    chk('rc_' + name + '_rearm', cmd(d, T.ARM, app.epoch))
"""

MAIN_PATH = """
import sys
from firmware import main as MAIN

class UartStub:
    def __init__(s):
        s.rec = False
        s.out = []
    def any(s):
        return 0
    def readinto(s, b, n=0):
        return 0
    def write(s, mv):
        if s.rec:
            s.out.append(bytes(mv))
        return len(mv)

class PinHal(Hal):
    # the HAL methods main.py and App.run use on a board, recorded
    def __init__(s, raise_at, exc):
        Hal.__init__(s)
        s.raise_at = raise_at
        s.exc = exc
        s.port = UartStub()
        s.marks = []
        s.wdt = 0
        s.feeds = 0
        s.stops = 0
        s.offs = 0
        s.resets = 0
    def read_encoder(s):
        s.n += 1
        if s.n == s.raise_at:
            s.port.rec = True
            raise s.exc
        return s.enc
    def estop(s):
        return False
    def wdt_start(s, ms):
        s.wdt = ms
    def wdt_feed(s):
        s.feeds += 1
    def wdt_stop(s):
        s.stops += 1
    def mark(s, c):
        s.marks.append(c)
    def reset(s):
        s.resets += 1
    def off(s):
        s.offs += 1
        s.duty = 0
        s.en = 0
    def uart(s):
        return s.port

class Board:
    CONFIG_DIR = DIR
    LINK = 'uart'
    def config(s):
        return {'watchdog_ms': 0, 'stall_ms': 0, 'wdt_ms': 100, 'epoch': 3}

for name, exc in (('exc', ValueError('boom')), ('kbd', KeyboardInterrupt())):
    hal = PinHal(60, exc)
    hal.adc = 2048 + 5
    raised = 0
    try:
        MAIN._robot(Board(), hal, 'uart', hal.port, 9, T.RC_POWER_ON)
    except KeyboardInterrupt:
        raised = 1
    chk(name + '_raised', raised)
    chk(name + '_wdt_ms', hal.wdt)
    chk(name + '_feeds', hal.feeds)
    chk(name + '_stops', hal.stops)
    chk(name + '_offs', hal.offs)
    chk(name + '_resets', hal.resets)
    chk(name + '_duty', hal.duty)
    chk(name + '_en', hal.en)
    chk(name + '_n_marks', len(hal.marks))
    chk(name + '_first_mark', hal.marks[0])
    chk(name + '_last_mark', hal.marks[-1])
    print('BYTES ' + name + ' ' + ''.join(['%02x' % x for x in b''.join(hal.port.out)]))
    # the next boot with the marker left: F_RESET latched, the cause in VERSION
    hal2, app2 = fresh(reset_cause=hal.marks[-1])
    arr = [0] * 8
    app2.fill_version(arr)
    chk(name + '_reboot_faults', app2.sup.faults)
    chk(name + '_reboot_cause', arr[4])
"""


def _parse(out: str) -> dict[str, int]:
    obs = {}
    for line in out.splitlines():
        if line.startswith("OBS "):
            _, k, v = line.split()
            obs[k] = int(v)
    return obs


@pytest.fixture(scope="module", params=["cpython", "unix"])
def obs(request) -> dict[str, int]:
    code = COMMON + SCENARIOS
    out = H.run_cpython(code) if request.param == "cpython" else run_unix(code, timeout=300)
    return _parse(out)


@pytest.fixture(scope="module")
def main_obs(tmp_path_factory) -> tuple[dict[str, int], str]:
    d = tmp_path_factory.mktemp("cfg")
    out = run_unix(COMMON + f"DIR = {str(d)!r}\n" + MAIN_PATH, timeout=120)
    return _parse(out), out


# ---------------------------------------------------------------- deadline rule
def test_balancing_starts_after_16_on_time_periods(obs) -> None:
    assert obs["period_us"] == 2000
    # step 1 measures nothing; steps 2..17 each close one on-time period
    assert obs["warmup_first_balancing_step"] == 17
    assert obs["warmup_faults"] == 0


def test_four_late_ticks_in_a_row_pass(obs) -> None:
    assert obs["late4_first_fault_step"] == -1
    assert obs["late4_n_late"] == 4
    assert obs["late4_state"] == S.BALANCING
    assert obs["late4_faults"] == 0


@pytest.mark.parametrize("k", [5, 8])
def test_the_fifth_late_tick_in_a_row_latches_deadline_and_cuts_the_motor(obs, k) -> None:
    # slow steps 30..30+k-1: the late starts are steps 31.., the 5th late start is step 35
    assert obs[f"late{k}_first_fault_step"] == 35
    assert obs[f"late{k}_fault_duty"] == 0
    assert obs[f"late{k}_fault_en"] == 0
    assert obs[f"late{k}_state"] == S.FAULT
    assert obs[f"late{k}_faults"] == S.F_DEADLINE
    assert obs[f"late{k}_bad"] == 0  # no non-zero duty / enable outside balancing, ever


def test_one_late_tick_in_26_is_sustainable_one_in_25_is_not(obs) -> None:
    assert obs["every26_first_fault_step"] == -1
    assert obs["every26_state"] == S.BALANCING
    # 1 in 25: +25 -24 a cycle; the score after the c-th late tick is 24 + c: > 100 at c = 77
    assert obs["every25_first_fault_step"] == 30 + 25 * 76 + 1
    assert obs["every25_n_late_at_fault"] == 77
    assert obs["every25_state"] == S.FAULT


def test_one_gap_over_10_periods_latches_at_once(obs) -> None:
    assert obs["gap9_first_fault_step"] == -1
    assert obs["gap9_state"] == S.BALANCING
    assert obs["gap11_first_fault_step"] == 31
    assert obs["gap11_state"] == S.FAULT
    assert obs["gap11_fault_duty"] == 0


def test_deadline_applies_while_armed_before_balancing(obs) -> None:
    assert obs["armed_first_balancing_step"] == -1
    assert obs["armed_first_fault_step"] == 35


def test_no_deadline_fault_while_disarmed_but_timing_measured_again(obs) -> None:
    assert obs["disarmed_faults"] == 0
    assert obs["disarmed_state"] == S.DISARMED
    assert obs["disarmed_n_late"] == 11
    # the last late start (step 41) was 19 on-time periods before the end: measured again
    assert obs["disarmed_timing_ok"] == 1
    # armed at step 5, warm after step 17; the late start at step 51 is one late tick (score 25),
    # no fault, no new warm-up once balancing
    assert obs["rewarm_first_balancing_step"] == 17
    assert obs["rewarm_faults"] == 0


def test_deadline_check_off_only_counts(obs) -> None:
    assert obs["nocheck_faults"] == 0
    assert obs["nocheck_n_late"] == 21


# ---------------------------------------------------------------- readiness
@pytest.mark.parametrize("name", ["crc", "shape"])
def test_a_bad_table_is_never_run(obs, name) -> None:
    assert obs[f"{name}_boot_faults"] == S.F_GAINS
    assert obs[f"{name}_boot_state"] == S.FAULT
    assert obs[f"{name}_boot_ready"] == 0
    assert obs[f"{name}_arm_faulted"] == T.R_FAULTED
    assert obs[f"{name}_clear"] == T.OK
    assert obs[f"{name}_cleared_state"] == S.DISARMED
    # cleared, the right epoch -- and still refused: not ready
    assert obs[f"{name}_arm_not_ready"] == T.R_NOT_READY
    assert obs[f"{name}_arm_not_ready_state"] == S.DISARMED
    assert obs[f"{name}_relatched_faults"] == S.F_GAINS
    assert obs[f"{name}_relatched_state"] == S.FAULT
    assert obs[f"{name}_loop_state"] == S.FAULT
    assert obs[f"{name}_loop_duty_sets_nonzero"] == 0


@pytest.mark.parametrize("name", ["crc", "shape"])
def test_only_a_good_upload_makes_the_board_usable(obs, name) -> None:
    assert obs[f"{name}_bad_upload"] == T.R_BAD_SHAPE
    assert obs[f"{name}_bad_upload_ready"] == 0
    assert obs[f"{name}_wrong_crc_upload"] == T.R_BAD_CRC
    assert obs[f"{name}_good_upload"] == T.OK
    assert obs[f"{name}_good_upload_ready"] == 1
    assert obs[f"{name}_good_upload_crc"] == 1
    assert obs[f"{name}_good_upload_faults"] == 0
    assert obs[f"{name}_after_upload_clear"] == T.OK
    assert obs[f"{name}_after_upload_arm"] == T.OK
    assert obs[f"{name}_after_upload_state"] in (S.ARMED, S.BALANCING)


def test_a_bad_upload_leaves_a_good_board_as_it_was(obs) -> None:
    assert obs["good_bad_upload"] == T.R_BAD_SHAPE
    assert obs["good_bad_upload_ready"] == 1
    assert obs["good_bad_upload_crc"] == 1
    assert obs["good_bad_upload_faults"] == 0


# ---------------------------------------------------------------- loop rate
def test_loop_rate_is_read_only(obs) -> None:
    for v in (250, 500, 1000):
        assert obs[f"rate_set_{v}"] == T.R_READ_ONLY
    assert obs["rate_set_direct"] == T.R_READ_ONLY
    assert obs["rate_set_low"] == T.R_OUT_OF_RANGE
    assert obs["rate_after"] == 1
    assert obs["rate_period_after"] == 1
    assert obs["rate_timing_period"] == 1
    assert obs["rate_other_param_ok"] == T.OK
    assert obs["rate_after_other"] == 1


# ---------------------------------------------------------------- reset cause
@pytest.mark.parametrize("name, rc", [("power_on", T.RC_POWER_ON), ("watchdog", T.RC_WATCHDOG),
                                      ("exception", T.RC_EXCEPTION)])
def test_reset_cause_latches_f_reset(obs, name, rc) -> None:
    assert obs[f"rc_{name}_version_cause"] == rc
    if rc == T.RC_POWER_ON:
        assert obs[f"rc_{name}_faults"] == 0
        assert obs[f"rc_{name}_state"] == S.DISARMED
        assert obs[f"rc_{name}_arm"] == T.OK
    else:
        assert obs[f"rc_{name}_faults"] == S.F_RESET
        assert obs[f"rc_{name}_state"] == S.FAULT
        assert obs[f"rc_{name}_arm"] == T.R_FAULTED
        assert obs[f"rc_{name}_rearm"] == T.OK  # cleared by clear_faults, nothing else wrong


# ---------------------------------------------------------------- main.py
def test_main_exception_path_motor_off_fault_reported_reset(main_obs) -> None:
    o, out = main_obs
    assert o["exc_raised"] == 0
    assert o["exc_wdt_ms"] == 100
    assert o["exc_feeds"] == 59  # one per completed tick, the 60th never completed
    assert o["exc_stops"] == 0  # the watchdog keeps running: the reset is the way out
    assert o["exc_offs"] >= 1
    assert o["exc_resets"] == 1
    assert o["exc_duty"] == 0 and o["exc_en"] == 0
    assert o["exc_first_mark"] == T.RC_WATCHDOG  # set when run() started the watchdog
    assert o["exc_last_mark"] == T.RC_EXCEPTION
    hexes = re.search(r"^BYTES exc (\w*)$", out, re.M).group(1)
    msgs = [m for m, _ in M.SerialStreamDecoder().feed(bytes.fromhex(hexes))]
    hb = [m for m in msgs if m.ID == T.HEARTBEAT]
    assert len(hb) == 1, msgs
    assert int(hb[0].faults) & S.F_LOOP
    assert int(hb[0].state) == S.FAULT
    assert o["exc_reboot_faults"] == S.F_RESET
    assert o["exc_reboot_cause"] == T.RC_EXCEPTION


def test_main_ctrl_c_stops_the_watchdog_and_clears_the_marker(main_obs) -> None:
    o, _ = main_obs
    assert o["kbd_raised"] == 1
    assert o["kbd_stops"] == 1
    assert o["kbd_resets"] == 0
    assert o["kbd_duty"] == 0 and o["kbd_en"] == 0
    assert o["kbd_last_mark"] == T.RC_POWER_ON
    assert o["kbd_reboot_faults"] == 0
    assert o["kbd_reboot_cause"] == T.RC_POWER_ON


# ---------------------------------------------------------------- one flag table
def _supervisor_flags() -> dict[str, int]:
    return {k[2:].lower(): v for k, v in vars(S).items() if k.startswith("F_") and isinstance(v, int)}


def test_supervisor_flags_are_the_message_table_faults() -> None:
    table = {name: bit for bit, name, _doc in T.FAULTS}
    assert _supervisor_flags() == table
    bits = sorted(table.values())
    assert all(b & (b - 1) == 0 for b in bits), "one bit per flag"
    assert len(set(bits)) == len(bits)
    assert max(bits) < 1 << 16  # HEARTBEAT.faults is a u16
    assert all(doc.strip() for _b, _n, doc in T.FAULTS)


def test_the_app_uses_the_supervisor_flags() -> None:
    # one definition of each fault flag: the supervisor's F_* constants, which are the bits the
    # protocol's fault table names; every other firmware module that names a flag imports it
    # (a module that wrote its own F_LOOP = const(128) would drift silently)
    import ast
    import importlib

    bits = {name: bit for bit, name, _doc in T.FAULTS}
    defined = {k: v for k, v in vars(S).items() if k.startswith("F_") and isinstance(v, int)}
    assert {k[2:].lower(): v for k, v in defined.items()} == bits
    used: dict[str, set[str]] = {}
    for path in sorted((ROOT / "firmware").glob("*.py")):
        if path.name == "supervisor.py":
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, (ast.Assign, ast.AnnAssign)):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                for t in targets:
                    if isinstance(t, ast.Name) and t.id in defined:
                        raise AssertionError(f"{path.name} defines its own {t.id}")
            if isinstance(node, ast.ImportFrom):
                for a in node.names:
                    if a.name in defined:
                        assert node.module in ("supervisor", "firmware.supervisor"), (path.name, node.module)
                        used.setdefault(path.stem, set()).add(a.name)
    # the app latches the flags it computes itself (deadline, e-stop, reset, config...)
    assert {"F_DEADLINE", "F_ESTOP", "F_RESET", "F_GAINS", "F_LOOP", "F_CONFIG", "F_UNDERVOLT",
            "F_ADC_OPEN"} <= set().union(*used.values()), used
    for mod, names in used.items():
        m = importlib.import_module(f"firmware.{mod}")
        for k in names:
            assert getattr(m, k) == bits[k[2:].lower()], (mod, k)


def test_docs_describe_every_fault_flag() -> None:
    text = (ROOT / "docs" / "firmware.md").read_text()
    m = re.search(r"^## Fault flags.*?(?=^## )", text, re.M | re.S)
    assert m, "docs/firmware.md has a '## Fault flags' section"
    sec = m.group(0)
    for bit, name, _doc in T.FAULTS:
        assert re.search(rf"\|\s*{bit}\s*\|\s*`{name}`", sec), f"fault flag {name} ({bit}) not in the table"
