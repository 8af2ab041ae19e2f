"""The firmware command dispatcher against a recording target (a test double).

A refused command answers NACK(id, reason, seq) and changes nothing; the real app
target is tested by the firmware engineer.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware import codec, commands
from firmware import msgtable as T
from firmware.supervisor import ARMED, BALANCING, DISARMED, F_GAINS, FAULT
from host.link import messages as M
from proto_helpers import RecordingSender, RecordingTarget


def _setup():
    tg = RecordingTarget()
    tx = RecordingSender()
    return tg, tx, commands.Dispatcher(tg, codec.Layout(), tx)


def _send(disp, msg, seq=0):
    buf = bytearray(2) + bytearray(msg.payload()) + bytearray(8)
    return disp.handle(msg.ID, seq, buf, 2)


def _refused(tx, msg, reason, seq=0):
    return tx.sent[-1] == (M.Nack(msg_id=msg.ID, reason=reason, seq=seq), seq)


@pytest.mark.parametrize(
    "msg, reason, prepare",
    [
        (M.SetReference(x_um=800001), T.R_OUT_OF_RANGE, None),
        (M.SetReference(x_um=-(2**31)), T.R_OUT_OF_RANGE, None),
        (M.SetReference(x_um=2**31 - 1), T.R_OUT_OF_RANGE, None),
        (M.ParamSet(index=T.P_WATCHDOG_MS, value=9), T.R_OUT_OF_RANGE, None),
        (M.ParamSet(index=T.P_TILT_LIMIT, value=2**31 - 1), T.R_OUT_OF_RANGE, None),
        (M.ParamSet(index=T.N_PARAMS, value=1), T.R_BAD_INDEX, None),
        (M.ParamGet(index=255), T.R_BAD_INDEX, None),
        (M.Arm(epoch=0), T.R_FAULTED, lambda tg: setattr(tg, "faults", 1)),
        (M.Arm(epoch=0), T.R_FAULTED, lambda tg: setattr(tg, "state", 3)),
        (M.Arm(epoch=1), T.R_STALE_EPOCH, None),
        (M.Arm(epoch=0), T.R_STALE_EPOCH, lambda tg: setattr(tg, "epoch", 255)),
        (M.GainsChunk(offset=0, data=bytes(6)), T.R_BAD_SEQUENCE, None),
        (M.GainsCommit(check=0), T.R_BAD_SEQUENCE, None),
        (M.GainsBegin(nbytes=0, crc=0, token=0), T.R_BAD_LENGTH, None),
        (M.GainsBegin(nbytes=T.GAINS_MAX + 1, crc=0, token=0), T.R_BAD_LENGTH, None),
        (M.GainsBegin(nbytes=6, crc=0, token=1), T.R_STALE_EPOCH, None),  # another session's upload
        (M.Arm(epoch=0, check=1), T.R_BAD_CHECK, None),  # a corrupted command: its check fails
        (M.SetReference(x_um=0, check=0), T.R_BAD_CHECK, None),
        (M.ParamSet(index=T.P_MAX_DUTY, value=5, check=bytes(3)), T.R_BAD_CHECK, None),
        (M.Request(msg_id=T.ACK), T.R_NOT_SUPPORTED, None),
        (M.Heartbeat(**{f.name: 0 for f in M.Heartbeat.FIELDS}), T.R_UNKNOWN, None),
        (M.Nack(msg_id=1, reason=1, seq=1), T.R_UNKNOWN, None),
    ],
)
def test_refused_with_reason_and_nothing_changes(msg, reason, prepare):
    tg, tx, disp = _setup()
    if prepare:
        prepare(tg)
    before = tg.snapshot()
    assert _send(disp, msg, seq=42) == reason
    assert _refused(tx, msg, reason, seq=42)
    assert tg.snapshot() == before
    assert not [c for c in tg.calls if c[0] != "gains_apply"]


def test_accepted_commands_reach_the_target():
    tg, tx, disp = _setup()
    assert _send(disp, M.SetReference(x_um=-800000), 1) == T.OK and tg.ref == -800000
    assert tx.sent[-1] == (M.Ack(msg_id=T.SET_REFERENCE, seq=1), 1)
    assert _send(disp, M.ParamSet(index=T.P_MAX_DUTY, value=1000), 2) == T.OK
    assert tx.sent[-1] == (M.ParamValue(index=T.P_MAX_DUTY, value=1000), 2)
    assert _send(disp, M.ParamSet(index=T.P_REF_LIMIT, value=100000)) == T.OK
    # the reference limit in force is the parameter, not a constant
    assert _send(disp, M.SetReference(x_um=100001)) == T.R_OUT_OF_RANGE and tg.ref == -800000
    assert _send(disp, M.Arm(epoch=tg.epoch)) == T.OK and tg.state == ARMED
    assert _send(disp, M.Request(msg_id=T.HEARTBEAT), 5) == T.OK
    assert tx.sent[-1] == (M.Heartbeat(state=1, faults=0, boot=7, epoch=tg.epoch, gains_crc=0x5A, uptime_ms=1234), 5)
    assert _send(disp, M.Request(msg_id=T.TELEM_CTRL)) == T.OK
    assert [m for m, _ in tx.sent[-2:]] == [M.TelemState(x=1, xdot=-2, phi=3, phidot=-4), M.TelemCtrl(ref=5, force=-6, duty=7, step_us=8)]
    # a sensor frame is not a command: left to the HIL HAL, no reply
    n = len(tx.sent)
    assert _send(disp, M.HilSensor(tick=1, adc=2, enc=3)) == -1 and len(tx.sent) == n


def _upload(disp, table: bytes, crc: int | None = None, nbytes: int | None = None):
    rs = [_send(disp, M.GainsBegin(nbytes=len(table) if nbytes is None else nbytes, crc=M.crc16(table) if crc is None else crc,
                                   token=disp.target.epoch))]
    for off in range(0, len(table), 6):
        rs.append(_send(disp, M.GainsChunk(offset=off, data=table[off:off + 6].ljust(6, b"\0"))))
    rs.append(_send(disp, M.GainsCommit(check=M.table_check(table))))
    return rs


def test_gain_table_upload():
    tg, tx, disp = _setup()
    table = bytes(range(200)) + b"\x01\x02\x03"
    assert _upload(disp, table) == [T.OK] * (2 + 34)
    assert tg.gains == table and tg.calls[-1] == ("gains_apply", len(table))
    # wrong CRC: refused, old table kept, target never called
    ncalls = len(tg.calls)
    assert _upload(disp, bytes(30), crc=1)[-1] == T.R_BAD_CRC
    assert tg.gains == table and len(tg.calls) == ncalls
    # wrong shape/unstable: the target refuses, the dispatcher relays its reason
    tg.gains_reason = T.R_UNSTABLE
    assert _upload(disp, bytes(30))[-1] == T.R_UNSTABLE and tg.gains == table
    assert _refused(tx, M.GainsCommit(check=M.table_check(bytes(30))), T.R_UNSTABLE)
    tg.gains_reason = 0
    # incomplete: commit before the last chunk
    _send(disp, M.GainsBegin(nbytes=12, crc=M.crc16(bytes(12)), token=tg.epoch))
    _send(disp, M.GainsChunk(offset=0, data=bytes(6)))
    assert _send(disp, M.GainsCommit(check=M.table_check(bytes(12)))) == T.R_INCOMPLETE
    # a repeated chunk (lost ACK) is ACKed again and not stored twice
    assert _send(disp, M.GainsChunk(offset=0, data=bytes(6))) == T.OK
    # out of order aborts the upload
    assert _send(disp, M.GainsChunk(offset=12, data=bytes(6))) == T.R_BAD_SEQUENCE
    assert _send(disp, M.GainsCommit(check=0)) == T.R_BAD_SEQUENCE
    # armed: refused, kept; the disarm ends the session (a new token), and the upload with it
    _send(disp, M.Arm(epoch=tg.epoch))
    rs = _upload(disp, bytes(range(12)))
    assert rs[-1] == T.R_ARMED and tg.gains == table
    _send(disp, M.Disarm())
    assert _send(disp, M.GainsCommit(check=M.table_check(bytes(range(12))))) == T.R_STALE_EPOCH and tg.gains == table
    assert _upload(disp, bytes(range(12)))[-1] == T.OK and tg.gains == bytes(range(12))
    # a table whose CRC-16 holds but whose CRC-32 does not (a corrupted commit): refused
    _send(disp, M.GainsBegin(nbytes=6, crc=M.crc16(bytes(range(6))), token=tg.epoch))
    _send(disp, M.GainsChunk(offset=0, data=bytes(range(6))))
    assert _send(disp, M.GainsCommit(check=M.table_check(bytes(range(6))) ^ 1)) == T.R_BAD_CHECK
    # motor off because of a latched fault: a table may be applied (fixes a gains fault)
    tg.state, tg.faults = FAULT, F_GAINS
    assert _upload(disp, bytes(range(6)))[-1] == T.OK and tg.gains == bytes(range(6))
    tg.state, tg.faults = BALANCING, 0
    assert _upload(disp, bytes(6))[-1] == T.R_ARMED and tg.gains == bytes(range(6))
    tg.state = DISARMED
    # declared length that a chunk cannot reach
    assert _upload(disp, bytes(6), nbytes=7)[-1] == T.R_INCOMPLETE


# no deadline: an example of 30 commands takes ~50 ms alone, several times that on a loaded
# machine (the integrity checks' CRC-32 in pure Python); what is tested is not the speed
@settings(max_examples=400, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 31), st.binary(min_size=8, max_size=8), st.integers(0, 255)), max_size=30))
def test_fuzz_dispatcher_never_raises_and_refusals_change_nothing(cmds):
    tg, tx, disp = _setup()
    layout = codec.Layout()
    for mid, payload, seq in cmds:
        if layout.plen[mid] == 255:
            continue  # the decoder never passes an unknown id
        before = tg.snapshot()
        ncalls = len(tg.calls)
        n = len(tx.sent)
        r = disp.handle(mid, seq, bytearray(2) + bytearray(payload), 2)
        if r > 0:
            assert tg.snapshot() == before
            assert tx.sent[-1][0] == M.Nack(msg_id=mid, reason=r, seq=seq)
            assert all(c[0] == "gains_apply" for c in tg.calls[ncalls:])
        elif r == 0 and mid != T.HOST_HEARTBEAT:
            # every accepted command is answered (HOST_HEARTBEAT: never, by design)
            assert len(tx.sent) > n
        # parameters always stay inside their documented range
        for p in T.PARAMS:
            assert p[3] <= tg.params[p[0]] <= p[4]
        if mid == T.SET_REFERENCE and r == 0:
            assert abs(tg.ref) <= tg.params[T.P_REF_LIMIT]
