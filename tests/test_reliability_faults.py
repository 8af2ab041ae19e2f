"""The fault injectors themselves (host/hil/faults.py): seeded, counted, doing what they say."""

from __future__ import annotations

import pytest

from firmware import msgtable as T
from host.link import messages as M
from host.hil.accounting import SeqAccount
from host.hil.faults import ActuatorFault, BusFaults, FaultError, FrameFaults, SensorFault, StreamFaults

SENSOR = M.BY_NAME["hil_sensor"]


def _frames(n: int) -> list[bytes]:
    return [M.encode_serial(SENSOR(tick=i, adc=2048, enc=i), i & 0xFF) for i in range(n)]


def test_clean_stream_passes_unchanged_even_split_anywhere() -> None:
    wire = b"".join(_frames(50))
    sf = StreamFaults("serial", seed=1)
    out = b"".join(sf(wire[i:i + 7]) for i in range(0, len(wire), 7))
    dec = M.SerialStreamDecoder()
    got = [m.tick for m, _ in dec.feed(out)]
    assert got == list(range(50))
    assert sf.counts["frames"] == 50 and sf.counts["passed"] == 50


def test_same_seed_same_faults_and_counts_add_up() -> None:
    wire = b"".join(_frames(2000))
    outs = []
    for _ in range(2):
        sf = StreamFaults("serial", seed=7, flip=0.03, drop=0.03, drop_byte=0.02, dup=0.01, reorder=0.01)
        outs.append((sf(wire), dict(sf.counts)))
    assert outs[0] == outs[1]
    out, c = outs[0]
    assert c["frames"] == 2000
    for k in ("dropped", "flipped", "byte_dropped", "duplicated", "reordered"):
        assert c[k] > 0, k
    dec = M.SerialStreamDecoder()
    got = [m.tick for m, _ in dec.feed(out)]
    # every intact frame decodes, no corrupted one does (CRC), duplicates appear twice
    assert len(got) == c["passed"]
    assert sum(dec.drops.values()) >= c["flipped"] + c["byte_dropped"]
    assert len(set(got)) == 2000 - c["dropped"] - c["flipped"] - c["byte_dropped"]
    # reordered frames arrive right after their successor
    assert any(b < a for a, b in zip(got, got[1:]))


def test_cut_swallows_everything_until_restored() -> None:
    f = _frames(3)
    sf = StreamFaults("serial", seed=0)
    sf.cut = True
    assert sf(f[0]) == b"" and sf.counts["cut"] == 1
    sf.cut = False
    assert M.SerialStreamDecoder().feed(sf(f[1]))[0][0].tick == 1


def test_bad_rates_refused() -> None:
    with pytest.raises(FaultError, match="flip"):
        FrameFaults(flip=1.5)
    with pytest.raises(FaultError, match="add up"):
        FrameFaults(drop=0.6, dup=0.6)
    with pytest.raises(FaultError, match="CAN"):
        StreamFaults("can", flip=0.1)
    with pytest.raises(FaultError, match="link"):
        StreamFaults("usb")


def test_bus_faults_drop_dup_reorder() -> None:
    class Bus:
        def __init__(self) -> None:
            self.i = 0

        def recv(self, timeout: float | None = None) -> int | None:
            self.i += 1
            return self.i if self.i <= 1000 else None

        def other(self) -> str:
            return "passed through"

    b = BusFaults(Bus(), seed=3, drop=0.05, dup=0.05, reorder=0.05)
    got = []
    while (m := b.recv(0.0)) is not None:
        got.append(m)
    c = b.counts
    assert len(got) == c["passed"] and c["dropped"] and c["duplicated"] and c["reordered"]
    assert c["frames"] == 1000
    # a frame held back for reordering when the stream ended is delivered by flush()
    held = b.faults.flush()
    assert len(set(got)) + len(held) == 1000 - c["dropped"]
    assert b.other() == "passed through"


@pytest.mark.parametrize("kind, check", [
    ("adc_low", lambda a, e, k: a == 0 and e == k),
    ("adc_high", lambda a, e, k: a == 4095 and e == k),
    ("adc_float", lambda a, e, k: 0 <= a <= 4095 and e == k),
    ("enc_stuck", lambda a, e, k: a == 2000 + k and e == 10),
    ("enc_jump", lambda a, e, k: e == (k + 4000) & 0xFFFF),
    ("delay", lambda a, e, k: e == max(0, k - 25) and a == 2000 + e),
])
def test_sensor_faults(kind: str, check) -> None:
    f = SensorFault(kind, 10)
    for k in range(100):
        a, e = f(k, 2000 + k, k)
        if k < 10:
            assert (a, e) == (2000 + k, k)
        else:
            assert check(a, e, k), (kind, k, a, e)
    assert f.applied == 90
    with pytest.raises(FaultError, match="unknown sensor fault"):
        SensorFault("adc_wobble", 0)


def test_actuator_fault() -> None:
    dead = ActuatorFault(5)
    stuck = ActuatorFault(5, "stuck")
    assert [dead(k, 100 + k) for k in range(8)] == [100, 101, 102, 103, 104, 0, 0, 0]
    assert [stuck(k, 100 + k) for k in range(8)] == [100, 101, 102, 103, 104, 104, 104, 104]
    with pytest.raises(FaultError):
        ActuatorFault(0, "smoke")


def test_seq_account_sees_gaps_duplicates_and_reorders() -> None:
    ts, tc, hb = M.BY_NAME["telem_state"], M.BY_NAME["telem_ctrl"], M.BY_NAME["heartbeat"]
    a = SeqAccount()
    st = ts(x=0, xdot=0, phi=0, phidot=0)
    ct = tc(ref=0, force=0, duty=0, step_us=0)
    h = hb(**{f.name: 0 for f in hb.FIELDS})
    seq = 250
    for i in range(20):  # wraps past 255
        s = (seq + i) & 0xFF
        if i == 7:
            continue  # lost
        if i % 5 == 0:
            a.add(h, s)
        else:
            a.add(st, s)
            if i != 9:
                a.add(ct, s)
    a.add(st, (seq + 3) & 0xFF)  # duplicate
    a.add(ct, (seq + 2) & 0xFF)  # duplicate
    a.add(M.BY_NAME["ack"](msg_id=T.ARM, seq=0), 3)  # not periodic: ignored
    s = a.stats()
    assert s["seq_span"] == 20 and s["seq_lost"] == 1 and s["duplicates"] == 2
    assert s["heartbeats"] == 4 and s["telemetry"] == 15 and s["half_pairs"] == 1
    assert s["reordered"] == 2
