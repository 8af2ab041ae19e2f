"""Issue 7, link faults, in the HIL loop: the real firmware under the MicroPython unix port on a
pty, serial and CAN framing, faults injected on the host side (host/hil/faults.py).

- link loss (real time: the firmware paces itself) -> watchdog cuts the motor within the
  configured timeout, the fault is reported when the link returns, resuming needs clear +
  re-arm;
- corrupted link (lockstep) -> no corrupted frame is ever acted on, the loop keeps balancing
  at 10 % frame faults, both sides count their drops, lost telemetry shows by sequence number.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from firmware import msgtable as T
from firmware.supervisor import ARMED, BALANCING, DISARMED, F_ENC_JUMP, F_TILT, F_TRACK, F_WATCHDOG, FAULT
from hil_probe import ProbeSession
from host.hil.faults import BusFaults, StreamFaults, Tap
from host.hil.lossy import run_lossy, stream_realtime
from host.hil.session import HilSession
from host.link.clients import CommandRefused
from sim.params import load_params
from sim.scenario import scenario_from_dict

P = load_params()
WD_MS = 200
HB_MS = next(p[5] for p in T.PARAMS if p[0] == T.P_HEARTBEAT_MS)
HOLD = scenario_from_dict({"name": "hold", "duration": 2.0, "initial": {"phi": 0.05}})


def _prepare_realtime(s: HilSession) -> None:
    L = s.link
    L.disarm()
    L.clear_faults()
    assert L.param_set("watchdog_ms", WD_MS) == WD_MS
    L.arm()


@pytest.mark.parametrize("link", ["serial", "can"])
def test_link_loss_watchdog_cuts_motor_within_timeout(link: str) -> None:
    # the host stops sending mid-balance; its receive side stays up, so the board's
    # heartbeats (state, uptime) show when the watchdog fired, in the board's own time
    tx, rx = StreamFaults(link), Tap(link)
    marks: dict[str, float] = {}

    def cut() -> None:
        tx.cut = True
        marks["cut"] = time.monotonic()

    with HilSession(link=link, mode="realtime", fault_tx=tx, fault_rx=rx) as s:
        _prepare_realtime(s)
        stream_realtime(s, 1.2, adc=P.pot_offset, at=[(0.5, cut)])
    hbs = [(t, m) for t, m, _ in rx.of("heartbeat")]
    before = [m for t, m in hbs if t < marks["cut"]]
    after = [m for t, m in hbs if t >= marks["cut"]]
    assert before and before[-1].state == BALANCING, before[-3:]
    u_lo = before[-1].uptime_ms  # the board's time at the cut is later than this
    u_hi = after[0].uptime_ms  # ... and earlier than this
    # no early trip: the watchdog cannot fire before WD_MS after the cut
    for m in after:
        if m.uptime_ms < u_lo + WD_MS:
            assert m.state == BALANCING, (u_lo, m)
    # and it did fire, within the timeout (+ one heartbeat period to be reported, + slack)
    first = next(m for m in after if m.state != BALANCING)
    assert first.state == FAULT and first.faults == F_WATCHDOG, first
    assert first.uptime_ms <= u_hi + WD_MS + HB_MS + 50, (u_hi, first)
    # motor off from the first faulted answer on (the answers are what drives the motor)
    acts = [m for _, m, _ in rx.of("hil_actuator")]
    assert any(a.state == BALANCING for a in acts)


@pytest.mark.parametrize("link", ["serial", "can"])
def test_link_loss_fault_reported_on_return_and_resume_needs_clear_and_rearm(link: str) -> None:
    tx, rx = StreamFaults(link), Tap(link)
    t_restore: list[float] = []

    def cut() -> None:
        tx.cut = rx.cut = True

    def restore() -> None:
        tx.cut = rx.cut = False
        t_restore.append(time.monotonic())

    with HilSession(link=link, mode="realtime", fault_tx=tx, fault_rx=rx) as s:
        _prepare_realtime(s)
        k = stream_realtime(s, 1.4, adc=P.pot_offset, at=[(0.4, cut), (1.0, restore)])
        L = s.link
        # back on the link: the first heartbeat and every answer report the latched fault
        back = [m for t, m, _ in rx.messages if t >= t_restore[0]]
        hb = next(m for m in back if m.NAME == "heartbeat")
        assert hb.state == FAULT and hb.faults & F_WATCHDOG, hb
        acts = [m for m in back if m.NAME == "hil_actuator"]
        assert acts and all(a.state == FAULT and a.duty == 0 and a.faults & F_WATCHDOG for a in acts), acts[:3]
        # the board does not resume by itself: arming is refused until the fault is cleared
        with pytest.raises(CommandRefused) as e:
            L.arm()
        assert e.value.reason == T.R_FAULTED
        assert L.query("heartbeat").state == FAULT
        L.clear_faults()
        hb = L.query("heartbeat")
        assert (hb.state, hb.faults) == (DISARMED, 0)
        # a stream alone does not restart the motor ...
        k = stream_realtime(s, 0.1, adc=P.pot_offset, start_tick=k)
        assert L.query("heartbeat").state == DISARMED
        # ... an explicit re-arm does
        L.arm()
        stream_realtime(s, 0.1, adc=P.pot_offset, start_tick=k)
        assert L.query("heartbeat").state == BALANCING


def _faults_from_tick0(*hooks):
    # the set-up (disarm, clear, arm...) runs on a clean link; the faults start at tick 0
    for h in hooks:
        h.faults.enabled = False

    def on_tick(k: int) -> None:
        if k == 0:
            for h in hooks:
                h.faults.enabled = True

    return on_tick


def _balanced(run, tail_s: float = 1.0) -> None:
    log = run.log
    n = int(tail_s * P.rate)
    st = log["fw_state"][log["answered"] == 1]
    assert set(st.tolist()) <= {ARMED, BALANCING}, set(st.tolist())
    assert st[-1] == BALANCING
    assert np.max(np.abs(log["phi"][-n:])) < 0.05, np.max(np.abs(log["phi"][-n:]))


def test_corrupted_serial_link_10pct_never_acted_on_keeps_balancing_counts_drops() -> None:
    rates = dict(flip=0.03, drop_byte=0.02, drop=0.02, dup=0.015, reorder=0.015)  # 10 % of frames
    tx = StreamFaults("serial", seed=11, **rates)
    rx = StreamFaults("serial", seed=12, **rates)
    s = ProbeSession(link="serial", fault_tx=tx, fault_rx=rx)
    s.open()
    try:
        run = run_lossy(s, HOLD, answer_timeout=0.005, on_tick=_faults_from_tick0(tx, rx))
        host_drops = dict(s.link.drops)
    finally:
        s.close()
    fw = s.probe()
    st = run.stats
    assert tx.counts["frames"] > 900 and tx.faults.corrupted > 25 and rx.faults.corrupted > 25
    # the firmware accepted exactly the frames that reached it intact (duplicates
    # included), refused every corrupted one, and counted them
    assert fw["n_ok"] == tx.counts["passed"], (fw, tx.counts)
    assert fw["n_crc"] + fw["n_length"] >= tx.faults.corrupted
    assert fw["alloc1"] == fw["alloc0"] and fw["locked"] == 1
    # the host likewise: no answer for a tick never sent, every corrupted frame counted
    assert st["bad_tick"] == 0
    assert sum(host_drops.values()) >= rx.faults.corrupted
    # lost telemetry/heartbeats are visible by sequence number
    assert st["seq_lost"] + st["half_pairs"] > 0
    assert st["seq_lost"] <= rx.counts["dropped"] + rx.faults.corrupted + rx.counts["reordered"]
    assert st["lost"] > 0 and st["stale"] > 0
    # and the loop kept balancing
    _balanced(run)


def test_corrupted_can_link_10pct_drop_dup_reorder_keeps_balancing() -> None:
    # on CAN a corrupted frame never reaches a node (the controller's CRC): it is a drop
    rates = dict(drop=0.05, dup=0.025, reorder=0.025)
    tx = StreamFaults("can", seed=21, **rates)
    s = ProbeSession(link="can", fault_tx=tx)
    s.open()
    try:
        bus = BusFaults(s.link.bus, seed=22, **rates)
        s.link.bus = bus
        run = run_lossy(s, HOLD, answer_timeout=0.005, on_tick=_faults_from_tick0(tx, bus))
    finally:
        s.close()
    fw = s.probe()
    assert tx.counts["dropped"] > 20 and bus.counts["dropped"] > 20
    assert fw["n_ok"] == tx.counts["passed"], (fw, tx.counts)
    assert fw["alloc1"] == fw["alloc0"]
    assert run.stats["bad_tick"] == 0 and run.stats["lost"] > 0
    _balanced(run)


@pytest.mark.slow
def test_link_beyond_what_the_loop_survives_fails_safe() -> None:
    # 60 % of the frames disturbed: whatever happens, nothing corrupted is acted on, and a
    # board that gives up is in FAULT with the motor off
    rates = dict(flip=0.2, drop_byte=0.1, drop=0.2, dup=0.05, reorder=0.05)
    tx = StreamFaults("serial", seed=31, **rates)
    rx = StreamFaults("serial", seed=32, **rates)
    s = ProbeSession(link="serial", fault_tx=tx, fault_rx=rx, timeout=4.0)
    s.open()
    try:
        run = run_lossy(s, scenario_from_dict({"name": "hold", "duration": 1.0, "initial": {"phi": 0.05}}),
                        answer_timeout=0.003, on_tick=_faults_from_tick0(tx, rx))
    finally:
        s.close()
    fw = s.probe()
    assert fw["n_ok"] == tx.counts["passed"]
    assert run.stats["bad_tick"] == 0
    log = run.log
    ok = log["answered"] == 1
    faulted = ok & (log["fw_state"] == FAULT)
    assert np.all(log["duty_fw"][faulted] == 0)
    # what trips is the tilt, the watchdog, or the encoder plausibility check (the cart
    # moved more between two accepted frames than it can in one tick) -- never the ADC
    # rail, which a corrupted reading acted on would most likely show
    allowed = F_TILT | F_WATCHDOG | F_ENC_JUMP | F_TRACK
    assert np.all(log["fw_faults"][faulted] & allowed == log["fw_faults"][faulted])
