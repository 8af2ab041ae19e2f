"""One test body per behaviour, run against every transport.

Transports: pyserial ``loop://``, a pty pair (both ends opened by pyserial), python-can
``virtual``, and python-can's ``serial`` interface over a pty pair (python-can parsing
the bytes).  The "board" peers run the firmware decoder, dispatcher and encoder
(CPython) so the host parses what firmware code wrote; test_proto_mpy.py repeats the
byte-level case with the real MicroPython interpreter.
"""

from __future__ import annotations

import itertools

import can
import pytest
import serial

from firmware import msgtable as T
from firmware.supervisor import F_ADC_RAIL
from host.link import clients as L
from host.link import messages as M
from proto_helpers import CanBoard, PtyBridge, SerialBoard

_chan = itertools.count()


def _samples() -> list[M.Message]:
    out = []
    for cls in M.MESSAGES.values():
        kw = {}
        for i, f in enumerate(cls.FIELDS):
            lo, hi = (0, 0) if f.is_raw else f.bounds
            kw[f.name] = bytes(range(1, f.size + 1)) if f.is_raw else (hi if i % 2 else lo + 1)
        out.append(cls(**kw))
    return out


@pytest.fixture(params=["loop", "pty", "virtual", "serialcan"])
def pair(request):
    """Two links that see each other's messages (the same link for loop://)."""
    kind = request.param
    closers = []
    if kind == "loop":
        a = b = L.SerialLink("loop://")
    elif kind == "virtual":
        ch = f"upright-pair-{next(_chan)}"
        a = L.CanLink(interface="virtual", channel=ch, node_id=1)
        b = L.CanLink(interface="virtual", channel=ch, node_id=1)
    else:
        br = PtyBridge()
        closers.append(br.close)
        if kind == "pty":
            a, b = L.SerialLink(br.a), L.SerialLink(br.b)
        else:
            a = L.CanLink(interface="serial", channel=br.a, node_id=1)
            b = L.CanLink(interface="serial", channel=br.b, node_id=1)
    yield a, b
    a.close()
    b.close()
    for c in closers:
        c()


def test_every_message_roundtrips(pair):
    a, b = pair
    for msg in _samples():
        a.send(msg)
        assert b.recv(timeout=2.0) == msg
        b.send(msg)
        assert a.recv(timeout=2.0) == msg
    assert a.recv(timeout=0) is None
    assert sum(a.drops.values()) == 0


@pytest.fixture(params=["pty", "virtual", "serialcan"])
def board(request):
    """(host link, board peer running the firmware dispatcher)."""
    kind = request.param
    if kind == "virtual":
        ch = f"upright-board-{next(_chan)}"
        bus = can.Bus(interface="virtual", channel=ch)
        peer = CanBoard(bus, node=1)
        host = L.CanLink(interface="virtual", channel=ch, node_id=1)
        yield host, peer
        host.close()
        peer.close()
        bus.shutdown()
        return
    br = PtyBridge()
    ser = serial.serial_for_url(br.b, timeout=0.02)
    if kind == "pty":
        peer = SerialBoard(ser.read, ser.write)
        host = L.SerialLink(br.a)
    else:
        peer = SerialBoard(ser.read, ser.write, can_node=1)
        host = L.CanLink(interface="serial", channel=br.a, node_id=1)
    yield host, peer
    host.close()
    peer.close()
    ser.close()
    br.close()


def test_commands_against_firmware_dispatcher(board):
    host, peer = board
    tg = peer.target
    kw = {"timeout": 1.0, "retries": 1}
    assert host.param_get("watchdog_ms", **kw) == 250
    assert host.param_set("watchdog_ms", 500, **kw) == 500 and tg.params[T.P_WATCHDOG_MS] == 500
    host.set_reference(0.125, **kw)
    assert tg.ref == 125000
    before = tg.snapshot()
    with pytest.raises(L.CommandRefused) as ei:
        host.set_reference(5.0, **kw)  # beyond the track
    assert ei.value.reason_name == "out_of_range" and ei.value.msg_id == T.SET_REFERENCE
    with pytest.raises(L.CommandRefused) as ei:
        host.param_set("watchdog_ms", 10**6, **kw)
    assert ei.value.reason == T.R_OUT_OF_RANGE
    with pytest.raises(L.CommandRefused) as ei:
        host.param_get(200, **kw)
    assert ei.value.reason == T.R_BAD_INDEX
    tg.faults = F_ADC_RAIL
    with pytest.raises(L.CommandRefused) as ei:
        host.arm(**kw)
    assert ei.value.reason_name == "faulted"
    assert tg.snapshot() == (before[0], F_ADC_RAIL, *before[2:])
    host.clear_faults(**kw)
    hb = host.query("heartbeat", **kw)
    assert (hb.state, hb.faults, hb.boot, hb.uptime_ms) == (0, 0, 7, 1234)
    assert host.query("timing", **kw).values() == (10, 20, 30, 0)
    ts = host.query("telem_state", **kw)
    assert ts.values() == (1, -2, 3, -4)
    assert host.expect("telem_ctrl", timeout=1.0).values() == (5, -6, 7, 8)
    table = bytes(range(47))
    host.upload_gains(table, **kw)
    assert tg.gains == table
    host.arm(**kw)
    with pytest.raises(L.CommandRefused) as ei:
        host.upload_gains(bytes(12), **kw)
    assert ei.value.reason_name == "armed" and tg.gains == table
    assert sum(host.drops.values()) == 0


def test_timeout_and_errors_are_link_errors():
    with L.SerialLink("loop://", check_identity=False) as link:
        # loop:// echoes the request, never an answer: retries then LinkTimeout
        with pytest.raises(L.LinkTimeout) as ei:
            link.request(M.ParamGet(index=0), timeout=0.01, retries=2)
        assert isinstance(ei.value, TimeoutError) and isinstance(ei.value, OSError)
        assert link.sent == 3
        # the echoed requests were not lost: they are still there to recv
        assert link.recv(timeout=0.5) == M.ParamGet(index=0)
    with pytest.raises(L.LinkClosed):
        link.send(M.Arm(epoch=0))
    with pytest.raises(L.LinkError) as ei:
        L.SerialLink("/dev/does-not-exist-upright")
    assert isinstance(ei.value.__cause__, serial.SerialException)
    with pytest.raises(L.LinkError) as ei:
        L.CanLink(interface="no-such-interface", channel="x")
    assert ei.value.__cause__ is not None
    with pytest.raises(TypeError):
        L.CanLink(can.Bus(interface="virtual", channel="t"), bitrate=5)
    with pytest.raises(ValueError):
        L.open_link("can:virtual")


def test_garbage_on_the_wire_is_counted_not_raised():
    with L.SerialLink("loop://") as link:
        good = M.encode_serial(M.Heartbeat(state=1, faults=0, boot=2, epoch=7, gains_crc=8, uptime_ms=3), 4)
        bad = bytearray(good)
        bad[3] ^= 0x40
        hb = M.Heartbeat(state=1, faults=0, boot=2, epoch=7, gains_crc=8, uptime_ms=3)
        # the first chunk of a port just opened may be the tail of a frame sent before: joined,
        # not a drop (M.SerialStreamDecoder, mid_stream); after a good frame, garbage is a drop
        link.write_raw(b"\x13\x37\x00" + good + b"\x13\x37" + bytes(bad) + good + b"\x00" * 5)
        assert link.recv(timeout=1.0) == hb
        assert link.recv(timeout=1.0) == hb
        assert link.recv(timeout=0.05) is None
        assert link.decoder.joined == 2
        assert link.drops["crc"] + link.drops["length"] == 2


def test_python_can_serial_garbage_is_dropped_not_fatal():
    br = PtyBridge()
    try:
        with serial.serial_for_url(br.b) as ser, L.CanLink(interface="serial", channel=br.a, node_id=1) as link:
            good = M.Heartbeat(state=1, faults=2, boot=3, epoch=4, gains_crc=5, uptime_ms=4)
            cid, data = M.encode_can(good, 1)
            frame = M.encode_serial_can(good, 1)
            # the same frame with one payload bit flipped: its CRC (timestamp field) fails
            flipped = bytearray(frame)
            flipped[10] ^= 0x10
            bad_dlc = b"\xaa" + bytes(4) + bytes([9]) + bytes(20)
            other_node = b"\xaa" + bytes(4) + bytes([8]) + M.can_id(2, good.ID).to_bytes(4, "little") + data + b"\xbb"
            ser.write(bad_dlc + other_node + bytes(flipped) + frame)
            ser.flush()
            got = None
            for _ in range(50):
                got = link.recv(timeout=0.1)
                if got is not None:
                    break
            assert got == good
            assert link.drops["length"] == 1 and link.drops["other"] == 1 and link.drops["crc"] == 1
    finally:
        br.close()


def test_python_can_serial_short_frame_is_dropped_and_a_slow_frame_still_arrives():
    """A frame cut short (a lossy line) is a counted framing drop, not an exception; a frame
    whose second half arrives 20 ms after its first (a loaded host) is received whole, and an
    idle recv() returns after its own timeout, not the port's."""
    import threading
    import time

    br = PtyBridge()
    try:
        with serial.serial_for_url(br.b) as ser, L.CanLink(interface="serial", channel=br.a, node_id=1) as link:
            good = M.Heartbeat(state=1, faults=0, boot=3, epoch=4, gains_crc=5, uptime_ms=6)
            frame = M.encode_serial_can(good, 1)
            t0 = time.monotonic()
            assert link.recv(timeout=0.02) is None
            assert time.monotonic() - t0 < 0.5
            ser.write(frame[:3])  # 0xAA and two of the four timestamp bytes, then nothing
            ser.flush()
            assert link.recv(timeout=0.3) is None
            assert link.drops["framing"] == 1

            def late_half() -> None:
                time.sleep(0.02)
                ser.write(frame[7:])
                ser.flush()

            ser.write(frame[:7])
            ser.flush()
            th = threading.Thread(target=late_half)
            th.start()
            got = link.recv(timeout=1.0)
            th.join()
            assert got == good
            assert link.drops["framing"] == 1
    finally:
        br.close()


def test_late_reply_to_an_earlier_request_is_not_taken_as_the_answer():
    import threading

    br = PtyBridge()
    try:
        # a scripted board that answers only this request (no VERSION): identity not checked
        with L.SerialLink(br.a, check_identity=False) as host, L.SerialLink(br.b) as board:
            def serve():
                req = board.recv(timeout=5.0)
                seq = board.last_seq
                board.write_raw(M.encode_serial(M.ParamValue(index=0, value=1), (seq + 100) & 0xFF))  # stale
                board.write_raw(M.encode_serial(M.ParamValue(index=0, value=2), seq))
                assert req == M.ParamGet(index=0)

            t = threading.Thread(target=serve)
            t.start()
            assert host.param_get(0, timeout=2.0, retries=0) == 2
            t.join()
            assert host.recv(timeout=1.0) == M.ParamValue(index=0, value=1)
    finally:
        br.close()


def test_frames_that_came_before_a_reply_are_observed_before_it(tmp_path):
    # the board's stream is in order on the wire: telemetry and a periodic heartbeat (disarmed) sent
    # before the reply to a host's request (balancing) must reach a board tool's listeners -- a
    # recorder labelling each row with the latest heartbeat -- before the reply does; they were once
    # queued behind it, and an excitation log recorded the ticks of before the arm as balancing and
    # excited (tests/test_readme_robot.py test_7)
    import threading

    from host.operate.board import Board
    from host.operate.record import Recorder

    br = PtyBridge()
    try:
        with L.SerialLink(br.a, check_identity=False) as host, L.SerialLink(br.b) as board:
            def serve():
                board.recv(timeout=5.0)
                seq = board.last_seq
                s0 = (seq + 50) & 0xFF  # periodic numbers that are not the request's
                frames = [(M.BY_NAME["telem_state"](x=10, xdot=0, phi=0, phidot=0), s0),
                          (M.BY_NAME["telem_ctrl"](ref=0, force=0, duty=0, step_us=199), s0),
                          (M.BY_NAME["heartbeat"](state=0, faults=0, boot=1, epoch=1, gains_crc=0, uptime_ms=100),
                           (s0 + 1) & 0xFF),
                          (M.BY_NAME["telem_state"](x=20, xdot=0, phi=0, phidot=0), (s0 + 2) & 0xFF),
                          (M.BY_NAME["telem_ctrl"](ref=0, force=0, duty=0, step_us=199), (s0 + 2) & 0xFF),
                          (M.BY_NAME["heartbeat"](state=2, faults=0, boot=1, epoch=1, gains_crc=0, uptime_ms=102), seq)]
                board.write_raw(b"".join(M.encode_serial(m, s) for m, s in frames))  # one write: one read

            t = threading.Thread(target=serve)
            t.start()
            b = Board(host, feed=False)
            seen: list[tuple[str, int | None]] = []
            b.listeners.append(lambda m, s, _t: seen.append((m.NAME, s)))
            rec = Recorder(b, tmp_path / "rows.csv")
            assert b.state(fresh=True)["state_name"] == "balancing"
            t.join()
            rec.close()
            assert [n for n, _ in seen] == ["telem_state", "telem_ctrl", "heartbeat", "telem_state", "telem_ctrl",
                                            "heartbeat"]
            assert seen[-1][1] is None and all(s is not None for _, s in seen[:-1])  # the reply last
            assert b.poll(0.2) == []  # nothing left queued to be observed a second time
            rows = (tmp_path / "rows.csv").read_text().splitlines()[1:]
            state = [int(r.split(",")[rec.columns.index("state")]) for r in rows]
            assert state == [-1, 0], rows  # no heartbeat yet, then the disarmed one: none says balancing
    finally:
        br.close()
