"""Gain-table upload (App.gains_apply) and the loop's own timing statistics, under MicroPython."""

from __future__ import annotations

import struct

import pytest

from firmware.msgtable import OK, R_ARMED, R_BAD_LENGTH, R_BAD_SHAPE, R_UNSTABLE
from firmware.supervisor import BALANCING
import fwharness as H
from host.design.discrete import controller_ss
from host.design.export import export
from host.boards.mpyrun import run_unix
from sim.params import load_params

P = load_params()
FD = export(P)
OFF = FD.offsets()


def _blob(flat) -> str:
    return struct.pack(f"<{len(flat)}i", *flat).hex()


def _patched(name: str, index: int, value: int) -> str:
    flat = FD.flat()
    flat[OFF[name][0] + index] = value
    return _blob(flat)


BLOBS = {
    "default": FD.blob().hex(),
    "ki": export(P, ki=30.0).blob().hex(),
    "soft": export(P, controller_ss(P, Q=(0.2, 0.5, 0.0, 0.0), R=1.0)).blob().hex(),
    "rate1000": export(P, controller_ss(P, rate=1000)).blob().hex(),  # delay 10 ticks: other shape
    "version": _patched("HDR", 0, 99),
    "huge_gain": _patched("KF", 3, 2**19),  # the force row would overflow a small int
    "huge_shift": _patched("SK", 0, 40),
    "big_int": FD.blob().hex()[:-8] + "ffffff7f",  # 2**31-1: not a small int
    "short": FD.blob().hex()[:-8],
}

SCRIPT = H.CHK_SRC + H.FAKE_HAL + f"""
from array import array
from firmware.app import App
BLOBS = {{k: bytes.fromhex(v) for k, v in {BLOBS!r}.items()}}
hal = Hal()
app = App(hal, config={{'watchdog_ms': 0}})
for name in ('version', 'huge_gain', 'huge_shift', 'big_int', 'short', 'rate1000', 'default', 'soft', 'ki'):
    b = BLOBS[name]
    buf = bytearray(1536)
    buf[:len(b)] = b
    chk('apply_' + name, app.gains_apply(buf, len(b)))
    chk('ki_after_' + name, app.ctrl.ki)
# refused while balancing, accepted again once disarmed
hal.adc = 2048
app.step()
app.cmd_arm()
app.step()
chk('state', app.sup.state)
b = BLOBS['default']
chk('apply_balancing', app.gains_apply(b, len(b)))
app.cmd_disarm()
chk('apply_disarmed', app.gains_apply(b, len(b)))
chk('ki_final', app.ctrl.ki)

# --- timing statistics with a scripted clock: exec 300 us, period 2000 us, one late step ---
class Clock(Hal):
    def __init__(s):
        Hal.__init__(s)
        s.seq = array('i', [0] * 64)
        s.i = 0
    def ticks_us(s):
        v = s.seq[s.i]
        s.i += 1
        return v
hal = Clock()
app = App(hal, config={{'watchdog_ms': 0}})
t = 0x3FFFFFFF - 5000  # across the 2**30 wrap of ticks_us
starts = (0, 2000, 4000, 7500, 9500, 11500)
execs = (300, 300, 2500, 300, 300, 100)
for k in range(6):
    hal.seq[2 * k] = (t + starts[k]) & 0x3FFFFFFF
    hal.seq[2 * k + 1] = (t + starts[k] + execs[k]) & 0x3FFFFFFF
for k in range(6):
    app.step()
arr = array('i', [0] * 4)
chk('t_jitter', app.timing.jitter_max)
app.fill_timing(arr)
chk('t_step_min', arr[0])
chk('t_step_max', arr[1])
chk('t_period_max', arr[2])
chk('t_overruns', arr[3])
chk('t_step_us', app.step_us)
app.fill_timing(arr)
chk('t_after_reset_max', arr[1])
""" + H.CHK_END


@pytest.fixture(scope="module")
def obs() -> dict[str, int]:
    return H.parse_ints(run_unix(SCRIPT, timeout=120))


def test_good_tables_are_applied(obs) -> None:
    assert obs["apply_default"] == OK and obs["apply_soft"] == OK and obs["apply_ki"] == OK
    assert obs["ki_after_default"] == 0 and obs["ki_after_ki"] != 0
    assert obs["apply_disarmed"] == OK and obs["ki_final"] == 0


@pytest.mark.parametrize(
    "name, reason",
    [("version", R_BAD_SHAPE), ("rate1000", R_BAD_LENGTH), ("huge_gain", R_UNSTABLE), ("huge_shift", R_UNSTABLE),
     ("big_int", R_UNSTABLE), ("short", R_BAD_LENGTH)],
)
def test_bad_tables_are_refused_and_change_nothing(obs, name, reason) -> None:
    assert obs[f"apply_{name}"] == reason
    assert obs[f"ki_after_{name}"] == 0  # still the default table


def test_upload_refused_while_balancing(obs) -> None:
    assert obs["state"] == BALANCING and obs["apply_balancing"] == R_ARMED


def test_timing_statistics(obs) -> None:
    assert obs["t_step_min"] == 100 and obs["t_step_max"] == 2500
    assert obs["t_period_max"] == 3500
    # the 2500 us step overran its 2000 us period, and its successor started 3500 us later
    assert obs["t_overruns"] == 2
    assert obs["t_jitter"] == 1500
    assert obs["t_step_us"] == 100
    assert obs["t_after_reset_max"] == 0
