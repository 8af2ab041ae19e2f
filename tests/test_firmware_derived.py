"""What the app derives, reports after disarm and says about its time, under MicroPython (issue 22).

* every limit derived from the active table follows a table change (upload or saved copy): the
  stall (no-motion) timeout, the link watchdog and the period in ticks of the new table's rate,
  not the boot table's -- a 1 kHz table on a 500 Hz boot table must stall out after stall_ms,
  not half of it;
* telemetry after a disarm (or a fault) reports the force applied (0) and the sensors at rest,
  not the last balancing tick's force and estimated speeds;
* uptime beyond 65.5 s is reported whole (status value uptime_ms; HEARTBEAT carries its low
  16 bits), and a restart of the loop without a reset (main.py after a MODE switch) keeps the
  board's uptime, reports the boot's reset cause without latching F_RESET again, and counts
  the start.
"""

from __future__ import annotations

import struct

import pytest

from firmware import msgtable as T
from firmware.supervisor import F_RESET, F_STALL
import fwharness as H
from host.boards.mpyrun import run_unix
from host.design.export import export
from sim.params import load_params

FD = export(load_params())
OFF = FD.offsets()


def _blob_rate(rate: int) -> str:
    flat = FD.flat()
    flat[OFF["RATE"][0]] = rate
    return struct.pack(f"<{len(flat)}i", *flat).hex()


SCRIPT = H.FAKE_HAL + f"""
import os
from array import array
from firmware import msgtable as T
from firmware.app import App
from firmware.store import ConfigStore
B1K = bytes.fromhex({_blob_rate(1000)!r})

def derived(app, tag):
    s = app.sup
    print(tag, app.rate, app.period_us, s.stall_ticks, s.wd_ticks, app.link_budget_us)

hal = Hal()
app = App(hal, config={{'watchdog_ms': 250, 'stall_ms': 100, 'epoch': 0}})
derived(app, 'boot')
buf = bytearray(B1K)
print('apply', app.gains_apply(buf, len(buf)))
derived(app, 'upload')
# the saved-copy path: a store holding the 1 kHz table, loaded by a fresh app at start-up
d = '@@DIR@@'
for n in ('cfg_a.bin', 'cfg_b.bin'):
    try:
        os.remove(d + '/' + n)
    except OSError:
        pass
st = ConfigStore(d)
st.save(app.params, app.table)
app2 = App(Hal(), config={{'watchdog_ms': 250, 'stall_ms': 100, 'epoch': 0}})
print('load', app2.attach_store(ConfigStore(d)))
derived(app2, 'loaded')
print('cfg', app2.status_get(T.S_CFG_STATUS), app2.status_get(T.S_CFG_SLOT), app2.status_get(T.S_CFG_SEQ))

# the stall timeout in board time: balancing with a pushed duty and a frozen encoder
hal = Hal()
app = App(hal, config={{'watchdog_ms': 0, 'stall_ms': 100, 'stall_duty': 1, 'epoch': 0}})
app.gains_apply(bytearray(B1K), len(B1K))
hal.adc = 2048 + 40
app.step()
app.cmd_arm()
app.sup.timing_ok = True
n = 0
while app.sup.state != 3 and n < 1000:
    app.step()
    n += 1
print('stall', n, app.sup.faults, app.period_us)

# telemetry after a disarm: force 0, rates 0, the sensors as read
hal = Hal()
app = App(hal, config={{'watchdog_ms': 0, 'stall_ms': 0, 'epoch': 0}})
hal.adc = 2048 + 30
app.step()
app.cmd_arm()
app.sup.timing_ok = True
for i in range(40):
    hal.enc = (hal.enc + 3) & 0xFFFF
    app.step()
arr = array('i', [0] * 8)
app.fill_telemetry(arr)
print('tel_bal', app.sup.state, ' '.join(str(v) for v in arr[:7]))
app.cmd_disarm()
app.step()
app.fill_telemetry(arr)
print('tel_dis', app.sup.state, ' '.join(str(v) for v in arr[:7]))
exp = array('i', [0] * 8)
s = app.sensors
print('tel_sens', app._tel(s.yx, 0), app._tel(s.yp, 2))

# uptime beyond 16 bits, a restart without a reset (main.py after MODE robot)
hal = Hal()
app = App(hal, config={{'epoch': 0, 'uptime_ms': 70000, 'reset_cause': T.RC_POWER_ON,
                        'reset_cause_boot': T.RC_WATCHDOG, 'starts': 2}})
app.step()
hb = array('i', [0] * 8)
app.fill_heartbeat(hb)
v = array('i', [0] * 8)
app.fill_version(v)
print('uptime', app.status_get(T.S_UPTIME_MS), hb[5], app.status_get(T.S_STARTS), v[4], app.sup.faults)
"""


@pytest.fixture(scope="module")
def out(tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[int]]:
    res = {}
    d = tmp_path_factory.mktemp("store")
    for line in run_unix(SCRIPT.replace("@@DIR@@", str(d)), timeout=60).splitlines():
        if line.strip():
            k, *v = line.split()
            res[k] = [int(x) for x in v]
    return res


def test_limits_follow_the_table_rate_on_upload_and_load(out) -> None:
    # rate, period_us, stall_ticks (100 ms), wd_ticks (250 ms), link budget (1.5 periods less
    # the larger of 1/8 period and admit.REFILL_US: 500 us at both rates)
    assert out["boot"] == [500, 2000, 50, 125, 2500]
    assert out["apply"] == [T.OK]
    assert out["upload"] == [1000, 1000, 100, 250, 1000]
    assert out["load"] == [0]  # store.LOADED
    assert out["loaded"] == [1000, 1000, 100, 250, 1000]
    assert out["cfg"] == [0, 0, 1]  # loaded, slot A, sequence 1


def test_stall_fires_after_stall_ms_of_the_new_rate(out) -> None:
    n, faults, period = out["stall"]
    assert faults & F_STALL and period == 1000
    assert 95 <= n * period / 1000 <= 110, f"stall after {n} ticks of {period} us"


def test_telemetry_after_disarm_reports_what_is_applied(out) -> None:
    st, x, xdot, phi, phidot, ref, force, duty = out["tel_bal"]
    assert st == 2 and force != 0 and duty != 0  # positive control: balancing pushes
    st, x, xdot, phi, phidot, ref, force, duty = out["tel_dis"]
    assert st == 0 and force == 0 and duty == 0 and xdot == 0 and phidot == 0
    assert [x, phi] == out["tel_sens"]


def test_uptime_whole_and_a_restart_without_reset(out) -> None:
    up, hb_low, starts, cause, faults = out["uptime"]
    assert up >= 70000 and hb_low == up & 0xFFFF
    assert starts == 2 and cause == T.RC_WATCHDOG and not faults & F_RESET
