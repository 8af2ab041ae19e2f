"""Supervisor transitions and fault latching, per case, under the MicroPython unix port.

One interpreter run plays every scenario on the real app with a scripted HAL and
prints named observations; each test below checks one case.  "Motor off within one
tick" means: on the very step that sees the cause, the duty handed to the HAL is 0
(and the step before it was not).
"""

from __future__ import annotations

import math

import pytest

from firmware.msgtable import OK, R_BAD_STATE, R_FAULTED, R_OUT_OF_RANGE
from firmware.supervisor import ARMED as ARM
from firmware.supervisor import BALANCING as BAL
from firmware.supervisor import DISARMED as DIS
from firmware.supervisor import F_ADC_RAIL as F_RAIL
from firmware.supervisor import F_ENC_JUMP as F_JUMP
from firmware.supervisor import F_STALL, F_TILT, F_TRACK
from firmware.supervisor import F_WATCHDOG as F_WD
from firmware.supervisor import FAULT as FLT
import fwharness as H
from host.design.export import export
from host.boards.mpyrun import run_unix
from sim.params import load_params

P = load_params()
FD = export(P)
CPR = 2**P.adc_bits / P.pot_range  # ADC counts per rad
OFF = P.pot_offset


def counts(rad: float) -> int:
    return OFF + int(round(rad * CPR))


SCRIPT = H.CHK_SRC + H.FAKE_HAL + f"""
from firmware.app import App
from firmware import supervisor as S
from firmware import msgtable as T

def fresh(stall=False, **cfg):
    # the fake HAL's encoder moves only when a test moves it: the no-motion check
    # (F_STALL, on by default) is switched off except where it is the subject
    hal = Hal()
    cfg.setdefault('watchdog_ms', 0)
    if not stall:
        cfg.setdefault('stall_ms', 0)
    app = App(hal, config=cfg)
    return hal, app

def balance(hal, app, tilt_counts={counts(0.02)}, ticks=20):
    hal.adc = {OFF}
    app.step()
    app.cmd_arm()
    hal.adc = tilt_counts
    for k in range(ticks):
        app.step()
    return app.sup.state

# --- arming window ---
hal, app = fresh()
chk('initial_state', app.sup.state)
chk('arm_reply', app.cmd_arm())
hal.adc = {counts(0.115)}
for k in range(10):
    app.step()
chk('armed_outside_window_state', app.sup.state)
chk('armed_outside_window_duty', hal.duty)
chk('armed_outside_window_sets', hal.n_set)
hal.adc = {counts(0.02)}
app.step()
chk('armed_inside_window_state', app.sup.state)

# --- tilt ---
hal, app = fresh()
balance(hal, app)
hal.adc = {counts(0.2)}
app.step()
app.step()
chk('tilt_before_duty_nonzero', hal.duty != 0)
hal.adc = {counts(0.49)}
app.step()
chk('tilt_below_limit_state', app.sup.state)
hal.adc = {counts(0.51)}
app.step()
chk('tilt_state', app.sup.state)
chk('tilt_faults', app.sup.faults)
chk('tilt_duty', hal.duty)
hal.adc = {OFF}
for k in range(5):
    app.step()
chk('tilt_latched_state', app.sup.state)
chk('tilt_latched_faults', app.sup.faults)
chk('tilt_latched_duty', hal.duty)
chk('tilt_arm_refused', app.cmd_arm())
chk('tilt_clear', app.cmd_clear_faults())
app.step()
chk('tilt_cleared_state', app.sup.state)
chk('tilt_cleared_faults', app.sup.faults)
chk('rearm', app.cmd_arm())
app.step()
chk('rearm_state', app.sup.state)
chk('clear_while_balancing', app.cmd_clear_faults())

# --- watchdog (250 ms at 500 Hz = 125 ticks) ---
hal, app = fresh(watchdog_ms=250)
balance(hal, app, ticks=100)
chk('wd_100_state', app.sup.state)
app.cmd_set_reference(0)
for k in range(125):
    app.step()
chk('wd_fed_125_state', app.sup.state)
app.step()
chk('wd_state', app.sup.state)
chk('wd_faults', app.sup.faults)
chk('wd_duty', hal.duty)
hal2, app2 = fresh(watchdog_ms=250)
for k in range(500):
    app2.step()
chk('wd_disarmed_state', app2.sup.state)
# a HAL that counts host frames (hal_hil) feeds the watchdog with every frame
hal3 = Hal()
hal3.n_sensor = 0
app3 = App(hal3, config={{'watchdog_ms': 250, 'stall_ms': 0}})
balance(hal3, app3, ticks=1)
for k in range(400):
    hal3.n_sensor += 1
    app3.step()
chk('wd_frames_state', app3.sup.state)

# --- ADC at a rail ---
for rail in (0, 4095):
    hal, app = fresh()
    balance(hal, app)
    hal.adc = {counts(0.1)}
    app.step()
    hal.adc = rail
    app.step()
    chk('rail%d_state' % rail, app.sup.state)
    chk('rail%d_faults' % rail, app.sup.faults)
    chk('rail%d_duty' % rail, hal.duty)
    chk('rail%d_clear' % rail, app.cmd_clear_faults())
    app.step()
    chk('rail%d_relatched' % rail, app.sup.faults)
hal, app = fresh()
hal.adc = 0
app.step()
chk('rail_disarmed_state', app.sup.state)
chk('rail_disarmed_arm', app.cmd_arm())

# --- encoder ---
hal, app = fresh()
hal.enc = 65530
balance(hal, app)
hal.enc = 10
app.step()
chk('enc_wrap_state', app.sup.state)
chk('enc_wrap_pos', app.sensors.pos)
hal.enc = 10 + {FD.tables['ENCJ'][0]}
app.step()
chk('enc_at_limit_state', app.sup.state)
hal.enc = hal.enc - {FD.tables['ENCJ'][0] + 1}
app.step()
chk('enc_jump_state', app.sup.state)
chk('enc_jump_faults', app.sup.faults)
chk('enc_jump_duty', hal.duty)

# --- track ---
hal, app = fresh()
balance(hal, app)
step = {FD.tables['ENCJ'][0] - 1}
for k in range(20000):
    hal.enc = (hal.enc + step) & 0xFFFF
    app.step()
    if app.sup.state != S.BALANCING:
        break
chk('track_state', app.sup.state)
chk('track_faults', app.sup.faults)
chk('track_pos', app.sensors.pos)
chk('track_duty', hal.duty)

# --- disarm cuts the motor at once ---
hal, app = fresh()
balance(hal, app)
hal.adc = {counts(0.2)}
app.step()
chk('disarm_before_duty_nonzero', hal.duty != 0)
chk('disarm_reply', app.cmd_disarm())
chk('disarm_duty_now', hal.duty)
app.step()
chk('disarm_state', app.sup.state)
chk('disarm_duty', hal.duty)
chk('disarm_in_fault_keeps_fault', 0)

# --- no-motion check (on by default): large duty, encoder frozen ---
for name, cfg in (('stall0', {{'stall_ms': 0}}), ('stall100', {{}})):
    hal, app = fresh(stall=True, **cfg)
    hal.adc = {OFF}
    app.step()
    app.cmd_arm()
    app.step()  # balancing from here
    chk(name + '_balancing', app.sup.state)
    hal.adc = {counts(0.2)}
    first, big = -1, 0
    for k in range(300):
        app.step()
        if first < 0 and app.sup.state == S.FAULT:
            first = k
        elif first < 0 and (hal.duty >= app.sup.stall_duty or hal.duty <= -app.sup.stall_duty):
            big += 1  # ticks with large duty (the encoder never moves)
    chk(name + '_state', app.sup.state)
    chk(name + '_faults', app.sup.faults)
    chk(name + '_first', first)
    chk(name + '_big', big)
    chk(name + '_duty', hal.duty)
chk('stall_ticks_default', app.sup.stall_ticks)
chk('stall_duty_default', app.sup.stall_duty)
hal, app = fresh(stall=True)
balance(hal, app)
hal.adc = {counts(0.2)}
for k in range(300):
    hal.enc = (hal.enc + (1 if k & 1 else -1)) & 0xFFFF
    app.step()
chk('stall_moving_state', app.sup.state)

# --- reference out of range ---
hal, app = fresh()
chk('ref_out_of_range', app.cmd_set_reference(900000))
chk('ref_ok', app.cmd_set_reference(-800000))
chk('ref_lsb', app.ref)
""" + H.CHK_END


@pytest.fixture(scope="module")
def obs() -> dict[str, int]:
    return H.parse_ints(run_unix(SCRIPT, timeout=120))


def test_arming_waits_for_upright(obs) -> None:
    assert obs["initial_state"] == DIS and obs["arm_reply"] == OK
    assert obs["armed_outside_window_state"] == ARM
    assert obs["armed_outside_window_duty"] == 0 and obs["armed_outside_window_sets"] == 10
    assert obs["armed_inside_window_state"] == BAL


def test_tilt_fault_cuts_the_motor_in_the_same_tick_and_latches(obs) -> None:
    assert obs["tilt_before_duty_nonzero"] == 1
    assert obs["tilt_below_limit_state"] == BAL
    assert obs["tilt_state"] == FLT and obs["tilt_faults"] == F_TILT and obs["tilt_duty"] == 0
    assert obs["tilt_latched_state"] == FLT and obs["tilt_latched_faults"] == F_TILT
    assert obs["tilt_latched_duty"] == 0
    assert obs["tilt_arm_refused"] == R_FAULTED
    assert obs["tilt_clear"] == OK and obs["tilt_cleared_state"] == DIS and obs["tilt_cleared_faults"] == 0
    assert obs["rearm"] == OK and obs["rearm_state"] == BAL
    assert obs["clear_while_balancing"] == R_BAD_STATE


def test_watchdog(obs) -> None:
    assert obs["wd_100_state"] == BAL
    assert obs["wd_fed_125_state"] == BAL  # fed by the command, 125 ticks = 250 ms allowed
    assert obs["wd_state"] == FLT and obs["wd_faults"] == F_WD and obs["wd_duty"] == 0
    assert obs["wd_disarmed_state"] == DIS  # not counting while disarmed
    assert obs["wd_frames_state"] == BAL  # host frames counted by the HAL feed it


@pytest.mark.parametrize("rail", [0, 4095])
def test_adc_at_rail(obs, rail) -> None:
    assert obs[f"rail{rail}_state"] == FLT and obs[f"rail{rail}_faults"] == F_RAIL
    assert obs[f"rail{rail}_duty"] == 0
    assert obs[f"rail{rail}_clear"] == OK and obs[f"rail{rail}_relatched"] == F_RAIL  # cause still there


def test_adc_rail_while_disarmed_blocks_arming(obs) -> None:
    assert obs["rail_disarmed_state"] == FLT and obs["rail_disarmed_arm"] == R_FAULTED


def test_encoder_wrap_and_jump(obs) -> None:
    assert obs["enc_wrap_state"] == BAL and obs["enc_wrap_pos"] == 16  # 65530 -> 10 is +16 counts
    assert obs["enc_at_limit_state"] == BAL
    assert obs["enc_jump_state"] == FLT and obs["enc_jump_faults"] == F_JUMP and obs["enc_jump_duty"] == 0


def test_track_limit(obs) -> None:
    track_counts = P.track * P.enc_cpr / (2 * math.pi * P.r_wheel)
    assert obs["track_state"] == FLT and obs["track_faults"] == F_TRACK and obs["track_duty"] == 0
    assert 1.2 * track_counts < obs["track_pos"] < 1.3 * track_counts


def test_disarm_cuts_the_motor_at_once(obs) -> None:
    assert obs["disarm_before_duty_nonzero"] == 1
    assert obs["disarm_reply"] == OK and obs["disarm_duty_now"] == 0
    assert obs["disarm_state"] == DIS and obs["disarm_duty"] == 0


def test_no_motion_check_on_by_default(obs) -> None:
    assert obs["stall0_balancing"] == obs["stall100_balancing"] == BAL
    assert obs["stall0_state"] == BAL and obs["stall0_faults"] == 0  # stall_ms=0: off
    assert obs["stall_ticks_default"] == 50 and obs["stall_duty_default"] == 800  # 100 ms at 500 Hz
    assert obs["stall100_state"] == FLT and obs["stall100_faults"] == F_STALL and obs["stall100_duty"] == 0
    # the duty of tick k is judged at tick k+1: 50 ticks of large duty without a count are
    # allowed, the tick after the 51st trips
    # (counted while the encoder stands still, whether or not the large-duty ticks are
    # consecutive: the counter only resets on an encoder count)
    assert obs["stall100_big"] == 51, (obs["stall100_big"], obs["stall100_first"])
    assert obs["stall_moving_state"] == BAL  # the encoder moves: no fault


def test_reference_limits(obs) -> None:
    assert obs["ref_out_of_range"] == R_OUT_OF_RANGE and obs["ref_ok"] == OK
    assert obs["ref_lsb"] * FD.lsb["x"] == pytest.approx(-0.8, abs=1e-5)
