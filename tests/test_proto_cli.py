"""``upright proto``: encode/decode hex in both framings, clear errors, dump a live link."""

from __future__ import annotations

import threading
import time

import pytest
import serial

from host.link import messages as M
from host.cli.main import main
from proto_helpers import PtyBridge


def _out(capsys, argv):
    rc = main(argv)
    cap = capsys.readouterr()
    return rc, cap.out.strip(), cap.err.strip()


def test_encode_decode_serial_and_can(capsys):
    rc, out, _ = _out(capsys, ["proto", "encode", "set_reference", "x_um=-0.5", "--physical", "--seq", "9"])
    assert rc == 0 and bytes.fromhex(out) == M.encode_serial(M.SetReference(x_um=-500000), 9)
    rc, dec, _ = _out(capsys, ["proto", "decode", out])
    assert rc == 0 and "seq   9" in dec and "set_reference(x_um=-0.5m, check=" in dec
    rc, out, _ = _out(capsys, ["proto", "encode", "gains_chunk", "offset=6", "data=010203040506", "--can", "--node", "2"])
    assert rc == 0 and out == f"{(2 << 5) | M.GainsChunk.ID:03X}#0600010203040506"
    rc, dec, _ = _out(capsys, ["proto", "decode", out, "--can"])
    assert rc == 0 and dec == "node 2  gains_chunk(offset=6B, data=010203040506)"
    rc, dec, _ = _out(capsys, ["proto", "decode", f"{(2 << 5) | M.Nack.ID:03X}#070205", "--can"])
    assert "(out_of_range)" in dec


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["proto", "encode", "param_get", "index=256"], "outside B range"),
        (["proto", "encode", "param_get"], "missing field"),
        (["proto", "encode", "param_get", "idx=1"], "no field 'idx'"),
        (["proto", "encode", "param_get", "index=x"], "expected an integer"),
        (["proto", "encode", "set_reference", "x_um=nan", "--physical"], "not finite"),
        (["proto", "encode", "warp"], "no message 'warp'"),
        (["proto", "decode", "zz"], "not hex"),
        (["proto", "decode", "123", "--can"], "ID#DATA"),
        (["proto", "decode", "03F#00", "--can"], "unknown message id 31"),
        (["proto", "decode", "02B#0304", "--can"], "payload of 2 bytes"),
        (["proto", "dump", "/dev/does-not-exist-upright"], "cannot open serial port"),
    ],
)
def test_bad_input_is_a_one_line_error(capsys, argv, needle):
    rc, _, err = _out(capsys, argv)
    assert rc == 1 and needle in err and len(err.splitlines()) == 1 and "Traceback" not in err


def test_decode_reports_drops(capsys):
    good = M.encode_serial(M.Arm(epoch=0), 1)
    bad = bytearray(good)
    bad[2] ^= 1
    rc, out, err = _out(capsys, ["proto", "decode", (bytes(bad) + good).hex()])
    assert rc == 1 and "arm(epoch=0, check=" in out and ("crc=1" in err or "length=1" in err)


def test_dump_a_live_pty(capsys):
    br = PtyBridge()
    msgs = [M.Heartbeat(state=2, faults=1, boot=3, epoch=5, gains_crc=6, uptime_ms=4), M.TelemState(x=1, xdot=2, phi=3, phidot=4)]
    stop = threading.Event()

    def board():
        # repeat until the dump has what it wants (opening a port flushes its input)
        with serial.serial_for_url(br.b) as ser:
            while not stop.is_set():
                ser.write(b"".join(M.encode_serial(m, i) for i, m in enumerate(msgs)))
                ser.flush()
                stop.wait(0.2)

    t = threading.Thread(target=board)
    t.start()
    try:
        rc, out, _ = _out(capsys, ["proto", "dump", br.a, "--count", "4", "--duration", "20"])
    finally:
        stop.set()
        t.join()
        br.close()
    lines = out.splitlines()
    assert rc == 0 and len(lines) == 4
    assert any("seq   0  heartbeat(state=2, faults=1, boot=3, epoch=5, gains_crc=6, uptime_ms=4ms)" in ln for ln in lines)
    assert any("seq   1  telem_state(x=0.0001m, xdot=0.002m/s" in ln for ln in lines)


def test_dbc_for_another_node(capsys):
    import cantools

    rc, out, _ = _out(capsys, ["proto", "dbc", "--node", "3"])
    db = cantools.database.load_string(out, "dbc")
    assert rc == 0 and db.get_message_by_name("heartbeat").frame_id == (3 << 5) | M.Heartbeat.ID
    rc, _, err = _out(capsys, ["proto", "dbc", "--node", "64"])
    assert rc == 2 and "0..63" in err
