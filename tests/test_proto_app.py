"""The dispatcher in front of the real firmware app (CPython): out-of-range and
wrong-state commands refused with a reason, and nothing in the app changes."""

from __future__ import annotations

import pytest

from firmware import codec, commands
from firmware import msgtable as T
from firmware.app import App
from firmware.supervisor import F_ADC_RAIL
import fwharness as H
from host.link import messages as M
from host.design.export import export
from proto_helpers import RecordingSender


def _Hal() -> H.StandInHal:
    return H.StandInHal(inc=2000)


def _setup():
    app = App(_Hal(), config={"watchdog_ms": 0})
    tx = RecordingSender()
    return app, tx, commands.Dispatcher(app, codec.Layout(), tx)


def _send(disp, msg, seq=0):
    return disp.handle(msg.ID, seq, bytearray(2) + bytearray(msg.payload()), 2)


def _state(app):
    return (app.sup.state, app.sup.faults, app.ref, app.ref_um, tuple(app.table), tuple(app.params))


def _upload(disp, blob: bytes, crc: int | None = None) -> int:
    r = _send(disp, M.GainsBegin(nbytes=len(blob), crc=M.crc16(blob) if crc is None else crc, token=disp.target.epoch))
    for off in range(0, len(blob), 6):
        r = r or _send(disp, M.GainsChunk(offset=off, data=blob[off:off + 6].ljust(6, b"\0")))
    return r or _send(disp, M.GainsCommit(check=M.table_check(blob)))


def test_reference_beyond_track_refused():
    app, tx, disp = _setup()
    lim = app.param_get(T.P_REF_LIMIT)
    assert _send(disp, M.SetReference(x_um=lim)) == T.OK and app.ref_um == lim
    before = _state(app)
    for x in (lim + 1, -lim - 1, 2**31 - 1, -(2**31)):
        assert _send(disp, M.SetReference(x_um=x), 3) == T.R_OUT_OF_RANGE
        assert tx.sent[-1] == (M.Nack(msg_id=T.SET_REFERENCE, reason=T.R_OUT_OF_RANGE, seq=3), 3)
        assert _state(app) == before


def test_arming_while_faulted_refused():
    app, tx, disp = _setup()
    app.sup.faults |= F_ADC_RAIL
    before = _state(app)
    assert _send(disp, M.Arm(epoch=app.epoch)) == T.R_FAULTED and _state(app) == before


@pytest.mark.parametrize("param, value", [("watchdog_ms", 5), ("tilt_limit_mrad", 2**31 - 1), ("max_duty", -1)])
def test_param_out_of_range_refused(param, value):
    app, tx, disp = _setup()
    before = _state(app)
    assert _send(disp, M.ParamSet(index=M.PARAMS[param][0], value=value)) == T.R_OUT_OF_RANGE
    assert _state(app) == before


def test_gain_table_upload_to_the_app():
    fd = export()
    blob = fd.blob()
    app, tx, disp = _setup()
    before = _state(app)
    # wrong CRC, wrong shape (truncated), corrupted limits: refused, table kept
    assert _upload(disp, blob, crc=M.crc16(blob) ^ 1) == T.R_BAD_CRC
    assert _upload(disp, blob[:-4]) == T.R_BAD_LENGTH
    bad = bytearray(blob)
    bad[4 * 30 + 3] = 0x7F
    assert _upload(disp, bytes(bad)) == T.R_UNSTABLE  # a value beyond the proven bounds
    shape = bytearray(blob)
    shape[4] ^= 1  # header: another controller order
    assert _upload(disp, bytes(shape)) == T.R_BAD_SHAPE
    assert _state(app) == before
    # armed: refused
    assert _send(disp, M.Arm(epoch=app.epoch)) == T.OK
    assert _upload(disp, blob) == T.R_ARMED and _state(app)[4] == before[4]
    _send(disp, M.Disarm())
    # the exported table itself is accepted
    assert _upload(disp, blob) == T.OK
    assert tx.sent[-1][0] == M.Ack(msg_id=T.GAINS_COMMIT, seq=0)
