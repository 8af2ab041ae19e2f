"""Issue 7, soak: a few simulated minutes of the lockstep HIL soak in make test (an hour in make soak)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from host.boards.mpyrun import ROOT
from host.hil.soak import SoakResult, _check, soak


@pytest.mark.slow
@pytest.mark.parametrize("link, seconds", [("serial", 180.0), ("can", 44.0)])
def test_short_soak(link: str, seconds: float) -> None:
    res = soak(seconds, link=link, chunk_s=22.0)
    assert res.ok, "\n".join(res.failures) + "\n" + res.table()
    s, p = res.stats, res.stats["probe"]
    # heap: locked for the whole run, nothing allocated
    assert p["locked"] == 1 and p["alloc0"] == p["alloc1"]
    assert p["steps"] == s["ticks"] + 1  # + the priming frame
    # clock: one period per tick, exactly
    assert s["uptime_advance_ms"] == s["ticks"] * s["period_ms"]
    # every telemetry pair accounted for
    assert s["telemetry"] == s["ticks"] // s["telem_div"]
    if link == "serial":
        assert s["seq_lost"] == 0 and s["duplicates"] == 0 and s["half_pairs"] == 0
    assert len(res.chunks) >= 2


def _fake(**over) -> SoakResult:
    chunk = {"t0": 0.0, "t1": 4.4, "rms_phi": 0.04, "peak_phi": 0.1, "rms_err": 0.1, "peak_duty": 12000.0,
             "step_us_mean": 14.0, "step_us_median": 13.0, "step_us_max": 40.0, "telemetry": 220.0, "ticks_per_s": 1e4, "not_balancing": 0.0}
    r = SoakResult(chunks=[dict(chunk), dict(chunk, t0=4.4, t1=8.8)])
    r.stats = {"ticks": 4400, "period_ms": 2.0, "uptime0_ms": 10, "uptime1_ms": 10 + 8800, "faults_seen": 0,
               "state_end": 2, "telem_div": 10, "telemetry": 440, "seq_lost": 0, "duplicates": 0, "half_pairs": 0,
               "host_drops": {}}
    for k, v in over.items():
        if k == "chunk1":
            r.chunks[1].update(v)
        else:
            r.stats[k] = v
    return r


PROBE = {"locked": 1, "alloc0": 100, "alloc1": 100, "n_crc": 0}


@pytest.mark.parametrize("over, probe, needle", [
    ({}, dict(PROBE, alloc1=132), "heap"),
    ({}, dict(PROBE, locked=0), "heap_lock"),
    ({}, dict(PROBE, n_crc=1), "decoder dropped"),
    ({"uptime1_ms": 10 + 8806}, PROBE, "timing drift"),
    ({"telemetry": 430}, PROBE, "telemetry"),
    ({"seq_lost": 1}, PROBE, "sequence"),
    ({"faults_seen": 2}, PROBE, "left balancing"),
    ({"chunk1": {"rms_phi": 0.06}}, PROBE, "rms_phi"),
    ({"chunk1": {"step_us_median": 40.0}}, PROBE, "firmware step"),
])
def test_soak_checks_can_fail(over, probe, needle: str) -> None:
    good = _fake()
    _check(good, PROBE, 0.1)
    assert good.ok, good.failures
    bad = _fake(**over)
    _check(bad, probe, 0.1)
    assert any(needle in f for f in bad.failures), bad.failures


@pytest.mark.slow
def test_soak_cli_refuses_too_short_in_one_line() -> None:
    r = subprocess.run([sys.executable, "-m", "host.cli", "soak", "--sim-seconds", "3", "--quiet"], cwd=ROOT,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "sim_seconds" in r.stderr
