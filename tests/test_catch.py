"""Catch mode for large tilts (issue 15 item 3; firmware/controller.py schedule, host/design/catch.py).

* firmware in the loop on the MicroPython unix port (virtual board): the report's 0.3 rad
  tilt recovered within 5 m/s^2 and settled within 2.5 s; the tracking design alone falls;
* the hand-back to the tracking row is bumpless (force step bounded) -- in-process runs of
  the same firmware code under CPython;
* zero allocation per tick with catch mode active and across the switches (heap locked);
* the catch path on the emulated RP2040 (test_catch_rp2040.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from host.bench.catch import run_tilt
import fwharness as H
from host.design.catch import CATCH_DEFAULT, physical_bound
from host.design.export import export
from host.hil.runs import run_scenarios
from sim.params import load_params
from sim.scenario import load_scenario

P = load_params()


def test_tilt_0p3_recovered_in_hil_on_the_unix_port(tmp_path) -> None:
    (run,) = run_scenarios([load_scenario("tilt_0p3")], out=tmp_path, gif=False, plot=False)
    summ = run.summary()
    m = summ.metrics
    checks = {c.name: c.status for c in summ.checks}
    assert checks["a_max"] == "PASS" and m.peak_xddot <= 5.0, m.peak_xddot
    assert checks["settle"] == "PASS" and m.settling_time < 2.5, m.settling_time
    assert m.peak_phi < 0.31  # caught at once: the tilt never grew past its start
    assert abs(float(run.log["phi"][-1])) < 0.01
    assert summ.as_expected


def test_tracking_design_alone_falls_and_catch_mode_recovers() -> None:
    off = run_tilt(0.3, fd=export(P, catch=None))
    on = run_tilt(0.3)
    assert not off.recovered and off.faults and off.n_catch == 0
    assert on.recovered and on.faults == 0 and on.n_catch == 1 and on.a_max <= 5.0
    # small tilts never enter catch mode: the shipped tracking behaviour is unchanged
    small = run_tilt(0.1)
    assert small.recovered and small.n_catch == 0


def test_handback_is_bumpless() -> None:
    r = run_tilt(0.3)
    fd = export(P)
    su = fd.lsb["u"]
    assert not math.isnan(r.handback_s), "no hand-back to the tracking row"
    assert r.handback_s < 2.0
    assert abs(r.bump_n) <= CATCH_DEFAULT.du + su
    log = r.log
    k = int(np.nonzero(np.diff(log["catch"].astype(int)) < 0)[0][0]) + 1  # first tracking tick
    us = log["u_sat"]
    step = abs(us[k] - us[k - 1])
    # the force moves by no more than an ordinary tick's change around the switch
    ordinary = float(np.max(np.abs(np.diff(us[k - 50:k - 1]))))
    assert step <= max(0.05, 2.0 * ordinary), (step, ordinary)
    # after the hand-back the pendulum stays upright and the cart returns to the reference
    # (the true tilt, 10 ms ahead of the estimate the switch uses, within a count of phi_off)
    assert np.max(np.abs(log["phi"][k:])) < CATCH_DEFAULT.phi_off + 0.01
    assert abs(float(log["phi"][-1])) < 0.01
    assert not log["catch"][k:].any()


def test_catch_table_entries_and_the_firmware_recheck() -> None:
    from firmware.controller import Controller
    from firmware.msgtable import OK, R_UNSTABLE

    fd = export(P)
    on, off, du, ulc, cphi, sphi, ucmax, rstep, woff = fd.tables["CATCH"]
    assert 0 < off < on and du > 0 and 0 < ulc < ucmax and cphi > 0
    assert rstep >= 1 and woff > 0
    assert export(P, catch=None).tables["CATCH"][0] == 0  # switched off
    assert physical_bound(P) == pytest.approx(math.atan(5.0 / 9.8))
    layout = H.layout_of(fd)
    flat = fd.flat()
    c = Controller(layout, flat)
    o = c.off["CATCH"]
    assert c.validate(flat, len(flat), fd.tables["HDR"][0]) == OK
    # an uploaded table is refused when its catch entries break the rule or the proof
    for j, v in ((1, on + 1), (0, fd.tables["LIM"][2] + 1), (6, ulc - 1), (4, 1 << 22), (8, -1)):
        bad = list(flat)
        bad[o + j] = v
        assert c.validate(bad, len(bad), fd.tables["HDR"][0]) == R_UNSTABLE, (j, v)
    bad = list(flat)
    bad[c.off["KFC"] + 2] = 1 << 21  # a catch gain over the headroom budget
    assert c.validate(bad, len(bad), fd.tables["HDR"][0]) == R_UNSTABLE


ALLOC = H.INTS_SRC + H.FAKE_HAL + """
from firmware.app import App
class G:
    pass
G.VERSION = %d
G.CRC = %d
G.LAYOUT = %r
G.FLAT = tuple(ints(%r))
hal = Hal()
app = App(hal, gains=G, config={'watchdog_ms': 0, 'arm_tilt_mrad': 500, 'stall_ms': 0})
c = app.ctrl
app.step()
app.cmd_arm()
ADC = (2048 + 300, 2048 + 250, 2048 - 280, 2048 + 5, 2048 - 3, 2048)
def ticks(n):
    for k in range(n):
        hal.adc = ADC[(k // 40) %% 6]
        hal.enc = (k * 3) & 0xFFFF
        app.step()
        if k %% 97 == 0:
            # a settled estimate: the hand-back test, then the reference ramp
            c.p[2] = 0
            c.p[3] = 0
            app.cmd_clear_faults()
            app.cmd_arm()
def extremes(rounds):
    # schedule() at the proof's bounds: estimate and stored forces at their limits, every
    # sign pattern, both modes, the reference at its limits
    lim = c.lim
    ub = c.ucmax if c.ucmax > c.ulim_t else c.ulim_t
    for rnd in range(rounds):
        for pat in range(64):
            for i in range(4):
                c.p[i] = lim[i] if (pat >> i) & 1 else -lim[i]
            if pat & 32:
                c.p[2] = 0
                c.p[3] = 0
            for i in range(c.d):
                c.b[i] = ub if (pat + i) & 16 else -ub
            c.integ = c.ilim if pat & 1 else -c.ilim
            c._use(pat & 2 == 0)
            c.rr = c.rlim if pat & 4 else -c.rlim
            c.ramp = True
            r = c.rlim if pat & 8 else -c.rlim
            c.step(c.p[0], c.p[2], c.schedule(r))
            c.step(c.p[0], c.p[2], c.schedule(r))
def control(n):
    for k in range(n):
        y = [k]
"""

PHASES = """
ticks(200)
n0 = c.n_catch
run('ticks', lambda: ticks(3000))
print('entries', c.n_catch - n0)
run('extremes', lambda: extremes(2))
run('control', lambda: control(200))
"""


def _alloc_code(run: str) -> str:
    fd = export(P)
    layout = tuple(H.layout_of(fd))
    return ALLOC % (fd.tables["HDR"][0], fd.crc(), layout, " ".join(map(str, fd.flat()))) + run + PHASES


@pytest.mark.interps("unix", "wasm")
def test_no_allocation_with_catch_mode_active(interp: H.Interp) -> None:
    # the unix port under heap_lock; the 32-bit WebAssembly port's small ints: an intermediate
    # of schedule() outside +-2**30 would be a heap big int (its probe counts the bytes)
    res = H.parse_ints(interp.run(_alloc_code(interp.alloc_run), timeout=300))
    if interp.name == "unix":
        assert res["control"] == 1  # the lock is real: a list allocation raised
    else:
        assert res["control"] > 0
    assert res["entries"] >= 5  # catch mode entered (and left) many times under the lock
    assert res["ticks"] == 0 and res["extremes"] == 0, res
