"""Saturation, anti-windup and no-wrap arithmetic of the firmware (MicroPython unix port).

Named scenarios in the PX4 style: the duty never leaves its range, the integrator does
not wind up while the force is saturated (recovery is quick), clamped arithmetic keeps
the sign instead of wrapping, the encoder position saturates.
"""

from __future__ import annotations

import numpy as np
import pytest

import fwharness as H
from host.design.discrete import simulate_loop
from host.design.export import export
from host.boards.mpyrun import run_unix
from sim.params import load_params

P = load_params()
FD = export(P)
# the integral/deadband table without catch mode: its random-tilt phase then stays on the
# tracking row (FD, with catch mode, covers the catch row's clamps in the same phase)
FD_KI = export(P, ki=40.0, deadband=500, catch=None)


SCRIPT = H.CHK_SRC + H.INTS_SRC + H.FAKE_HAL + H.gains_src("G0", FD) + H.gains_src("G1", FD_KI) + """
from firmware.app import App
from firmware import msgtable as T
from firmware.supervisor import BALANCING

# --- duty within range: random sensor readings while balancing, both tables ---
seed = 12345
def rnd(n):
    global seed
    seed = (seed * 1103515245 + 12345) & 0x3FFFFFFF
    return (seed >> 8) % n
for gi, g in enumerate((G0, G1)):
    for max_duty in (32767, 12000):
        hal = Hal()
        app = App(hal, gains=g, config={'watchdog_ms': 0, 'tilt_limit_mrad': 1500, 'max_duty': max_duty})
        lo = 0
        hi = 0
        nbal = 0
        for k in range(3000):
            if app.sup.state != BALANCING:
                app.cmd_disarm()
                app.cmd_clear_faults()
                hal.adc = 2048
                app.step()
                app.cmd_arm()
            hal.adc = 2048 - 1200 + rnd(2401)
            # the encoder: a random walk, and every 600 ticks 150 ticks of a steady run at
            # 1-1.3 m/s each way (a speed estimate the estimator believes, whatever its speed,
            # so that the back-EMF term drives the duty to its limit)
            ph = (k // 150) % 4
            step = 30 + rnd(11) if ph == 1 else (-30 - rnd(11) if ph == 3 else rnd(81) - 40)
            hal.enc = (hal.enc + step) & 0xFFFF
            d = app.step()
            if app.sup.state == BALANCING:
                nbal += 1
            if d < lo:
                lo = d
            if d > hi:
                hi = d
        chk('duty_lo_%d_%d' % (gi, max_duty), lo)
        chk('duty_hi_%d_%d' % (gi, max_duty), hi)
        chk('duty_nbal_%d_%d' % (gi, max_duty), nbal)

# --- motor mapping extremes ---
hal = Hal()
app = App(hal, gains=G1, config={'watchdog_ms': 0})
m = app.motor
c = app.ctrl
chk('motor_max', m.duty(c.ulim, c.lim[1]))
chk('motor_min', m.duty(-c.ulim, -c.lim[1]))
chk('motor_zero', m.duty(0, 0))
chk('motor_small_pos', m.duty(1, 0))
chk('motor_small_neg', m.duty(-1, 0))

# --- anti-windup: force held in saturation for 2000 ticks by a tiny force limit ---
ulim = c.ulim
r = c.rlim >> 1
for aw in (1, 0):
    c.reset(0, 0)
    c.aw = aw == 1
    c.ulim = 50
    c.uhi = 50  # the live clamp (tracking row: +-ulim)
    c.ulo = -50
    sat = 0
    for k in range(2000):
        u = c.step(0, 0, r)
        if u == 50 or u == -50:
            sat += 1
    chk('aw%d_sat_ticks' % aw, sat)
    chk('aw%d_integ_after' % aw, c.integ)
    # the cause goes away: full force range back, measurement at the reference
    c.ulim = ulim
    c.uhi = ulim
    c.ulo = -ulim
    rec = -1
    for k in range(1000):
        u = c.step(0, 0, 0)
        if rec < 0 and -200 < u < 200:
            rec = k
    chk('aw%d_recovery_ticks' % aw, rec)
c.aw = True
chk('aw_ilim', c.ilim)

# --- no wrap: inputs far beyond the limits keep the right sign ---
c.reset(0, 0)
for k in range(500):
    u = c.step(1 << 24, 1 << 24, c.rlim)
    for i in range(4):
        if c.p[i] > c.lim[i] or c.p[i] < -c.lim[i]:
            chk('nowrap_state_out_of_range', 1)
chk('nowrap_u_pos_inputs', u)
c.reset(0, 0)
for k in range(500):
    u = c.step(-(1 << 24), -(1 << 24), -c.rlim)
chk('nowrap_u_neg_inputs', u)
chk('nowrap_ulim', c.ulim)

# --- the encoder position saturates instead of wrapping ---
s = app.sensors
s.zero()
e = 0
for k in range(200000):
    e = (e + 40) & 0xFFFF
    s.update(2048, e)
chk('enc_pos_after_8M_counts', s.pos)
""" + H.CHK_END


@pytest.fixture(scope="module")
def obs() -> dict[str, int]:
    return H.parse_ints(run_unix(SCRIPT, timeout=180))


@pytest.mark.parametrize("g", [0, 1])
@pytest.mark.parametrize("max_duty", [32767, 12000])
def test_duty_never_outside_its_range(obs, g, max_duty) -> None:
    assert obs[f"duty_nbal_{g}_{max_duty}"] > 1000  # mostly balancing, not faulted
    assert -max_duty <= obs[f"duty_lo_{g}_{max_duty}"] and obs[f"duty_hi_{g}_{max_duty}"] <= max_duty
    assert obs[f"duty_lo_{g}_{max_duty}"] == -max_duty or obs[f"duty_hi_{g}_{max_duty}"] == max_duty  # reached


def test_motor_mapping_extremes_and_deadband(obs) -> None:
    assert obs["motor_max"] == 32767 and obs["motor_min"] == -32767 and obs["motor_zero"] == 0
    assert obs["motor_small_pos"] >= 500 and obs["motor_small_neg"] <= -500  # deadband 500 added


def test_integrator_does_not_wind_up(obs) -> None:
    assert obs["aw1_sat_ticks"] == 2000 and obs["aw0_sat_ticks"] == 2000
    # conditional integration: nothing accumulated in the saturating direction
    assert abs(obs["aw1_integ_after"]) <= obs["aw_ilim"] // 100
    assert 0 <= obs["aw1_recovery_ticks"] <= 25  # back within 50 ms
    # the counterfactual shows the test can fail: without it the integrator winds up to
    # its clamp and the force stays off (it never unwinds at zero error)
    assert abs(obs["aw0_integ_after"]) == obs["aw_ilim"]
    assert obs["aw0_recovery_ticks"] == -1


def test_clamped_arithmetic_keeps_the_sign(obs) -> None:
    assert "nowrap_state_out_of_range" not in obs
    assert abs(obs["nowrap_u_pos_inputs"]) == obs["nowrap_ulim"]
    assert obs["nowrap_u_neg_inputs"] == -obs["nowrap_u_pos_inputs"]


def test_encoder_position_saturates(obs) -> None:
    assert obs["enc_pos_after_8M_counts"] == 0x3FFFFF


def test_integral_action_removes_the_offset_of_a_constant_push() -> None:
    push = lambda t: 0.5  # noqa: E731
    no_i = simulate_loop(P, FD.ctrl, [0, 0, 0, 0], 10.0, quantise=True, disturbance=push,
                         controller=H.fixed_controller(P, FD))
    with_i = simulate_loop(P, FD.ctrl, [0, 0, 0, 0], 10.0, quantise=True, disturbance=push,
                           controller=H.fixed_controller(P, export(P, ki=6.0)))
    off_no_i = np.mean(np.abs(no_i["x"][-500:]))
    off_i = np.mean(np.abs(with_i["x"][-500:]))
    assert off_no_i > 0.005 and off_i < off_no_i / 5
    assert np.max(np.abs(with_i["phi"])) < 0.05
