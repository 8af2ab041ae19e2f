"""Identity, stats and liveness on the link (issue 13 items 3, 7 and 9).

* VERSION: the firmware reports the generated table hashes, the active gain CRC and the
  reset cause; the host refuses a board whose message-table hash differs from its own.
* STATS_DECODE / STATS_FRAMES / STATS_LOOP: the decoder's counters by cause, frames in and
  out, worst step, deadline misses, free heap -- on request, allocation-free.
* The host's heartbeat: sent while the link operates the board; a board heartbeat missing
  for 3 periods is flagged.
"""

from __future__ import annotations

import time
from array import array

import can
import pytest

from firmware import codec, commands, framing, identity
from firmware import msgtable as T
from firmware.app import App
import fwharness as H
from host.boards.mpyrun import micropython_exe, run_unix
from host.link import clients as L
from host.link import identity as ID
from host.link import messages as M
from proto_helpers import CanBoard


def test_generated_identity_is_the_tables_hash():
    assert identity.TABLE_HASH == ID.table_hash() and identity.PARAM_HASH == ID.param_hash()
    assert identity.FW_VERSION == ID.fw_version()
    # only what the wire depends on is hashed: the canonical text has no doc strings
    assert T.MESSAGES[0][3] not in ID.table_canon()


def _bus_pair(name: str):
    return can.Bus(interface="virtual", channel=name), can.Bus(interface="virtual", channel=name)


def test_host_refuses_a_board_with_another_message_table(monkeypatch):
    a, b = _bus_pair("identity-other")
    board = CanBoard(b)
    try:
        with L.CanLink(a, node_id=1) as link:
            v = link.identify(timeout=1.0)
            assert v.table_hash == ID.table_hash()
            # the same board built from another table
            monkeypatch.setattr(identity, "TABLE_HASH", ID.table_hash() ^ 0x0100)
        with L.CanLink(a, node_id=1) as link:
            with pytest.raises(L.IncompatibleBoard) as ei:
                link.arm(timeout=0.5, retries=1)
            assert "message table" in str(ei.value) and "refusing to operate" in str(ei.value)
            assert ei.value.version is not None and not link.heartbeat_running
            for cmd in (link.disarm, link.clear_faults):
                with pytest.raises(L.IncompatibleBoard):
                    cmd(timeout=0.5, retries=1)
        # nothing reached the board's target
        assert board.target.calls == []
    finally:
        board.close()
        a.shutdown()
        b.shutdown()


def _Hal() -> H.StandInHal:
    return H.StandInHal(inc=2000)


def test_version_and_stats_report_what_the_board_knows():
    layout = codec.Layout()
    app = App(_Hal(), config={"pot_offset": 2048})
    app.gains_crc = 0xBEEF
    app.reset_cause = 3
    out = bytearray()
    tx = framing.SerialTx(framing.Encoder(layout), lambda buf, n: out.extend(buf[:n]))
    dec = framing.Decoder(layout)
    disp = commands.Dispatcher(app, layout, tx)
    disp.dec = dec
    for _ in range(50):
        app.step()
    bad = bytearray(M.encode_serial(M.ParamGet(index=0), 1))
    bad[3] ^= 4
    unknown = b"\x00" + M.cobs_encode(b"\x1f\x00" + M.crc16(b"\x1f\x00").to_bytes(2, "big")) + b"\x00"
    stream = bytes(bad) + unknown + M.encode_serial(M.Request(msg_id=T.VERSION), 2) \
        + M.encode_serial(M.Request(msg_id=T.STATS_DECODE), 3)
    for x in stream:
        m = dec.feed(x)
        if m >= 0:
            disp.handle(m, dec.seq, dec.buf, 2)
    got = {type(m).NAME: m for m, _ in M.SerialStreamDecoder().feed(bytes(out))}
    v = got["version"]
    assert (v.fw_version, v.table_hash, v.param_hash, v.gains_crc, v.reset_cause) == \
        (ID.fw_version(), ID.table_hash(), ID.param_hash(), 0xBEEF, 3)
    d = got["stats_decode"]
    assert (d.crc, d.length, d.unknown, d.framing) == (dec.n_crc, dec.n_length, dec.n_unknown, dec.n_overrun)
    assert d.crc >= 1 and d.unknown == 1
    f = got["stats_frames"]
    assert f.frames_in == 2 and f.frames_out == 2  # version and stats_decode went before it
    lp = got["stats_loop"]
    assert lp.step_max_us == max(app.timing.worst, app.timing.step_max) > 0
    assert lp.overruns == app.timing.misses + app.timing.overruns
    # the heartbeat: the epoch and the gain CRC's low byte
    hb = array("i", [0] * 8)
    app.fill_heartbeat(hb)
    assert hb[3] == app.epoch & 0xFF and hb[4] == 0xEF


def test_since_boot_figures_survive_a_timing_report():
    app = App(_Hal(), config={"pot_offset": 2048})
    app.timing.end(0, 5000)  # one long step
    arr = array("i", [0] * 8)
    app.fill_timing(arr)  # the TIMING interval restarts ...
    app.fill_stats(arr)  # ... STATS_LOOP keeps the worst since boot
    assert arr[0] >= 5000 and arr[1] >= 1


_LOCKED = H.FAKE_HAL + """
import gc, micropython
from array import array
from firmware import codec, commands, framing
from firmware.app import App

class Sink:
    n = 0
    def write(self, buf, n):
        self.n += 1

layout = codec.Layout()
hal = Hal()
hal.inc = 2000
app = App(hal, config={"pot_offset": 2048})
sink = Sink()
dec = framing.Decoder(layout)
disp = commands.Dispatcher(app, layout, framing.SerialTx(framing.Encoder(layout), sink.write))
disp.dec = dec
data = %r
n = len(data)
def run():
    i = 0
    while i < n:
        m = dec.scan(data, i, n)
        i = dec.next
        if m >= 0:
            disp.handle(m, dec.seq, dec.buf, 2)
run()
gc.collect()
a = gc.mem_alloc()
micropython.heap_lock()
run()
micropython.heap_unlock()
print(gc.mem_alloc() - a, sink.n)
"""


def test_version_stats_and_host_heartbeat_allocate_nothing_under_the_heap_lock():
    if not micropython_exe():
        pytest.skip("MicroPython unix port not installed")
    msgs = [M.Request(msg_id=T.VERSION), M.Request(msg_id=T.STATS_DECODE), M.HostHeartbeat(),
            M.Arm(epoch=0), M.Disarm(), M.Request(msg_id=T.HEARTBEAT)]
    data = b"".join(M.encode_serial(m, i) for i, m in enumerate(msgs)) * 20
    out = run_unix(_LOCKED % data).split()
    assert int(out[0]) == 0
    assert int(out[1]) > 2 * 20 * 5


def test_host_heartbeat_flows_and_a_silent_board_is_flagged():
    a, b = _bus_pair("identity-silence")
    seen: list[float] = []
    try:
        with L.CanLink(a, node_id=1, check_identity=False) as link:
            link.on_silent = seen.append
            link.start_heartbeat(period=0.02, board_period=0.05)
            t0 = time.monotonic()
            n_hb = 0
            while time.monotonic() - t0 < 0.5:
                f = b.recv(0.05)
                if f is not None and f.arbitration_id == M.can_id(1, T.HOST_HEARTBEAT):
                    n_hb += 1
            assert n_hb >= 10
            # no board heartbeat for > 3 periods: flagged once
            assert link.board_silent and link.silences == 1 and seen and seen[0] > 0.15
            # a heartbeat from the board clears the flag
            cid, data = M.encode_can(M.Heartbeat(**{f.name: 0 for f in M.Heartbeat.FIELDS}), 1)
            b.send(can.Message(arbitration_id=cid, data=data, is_extended_id=False))
            assert isinstance(link.recv(timeout=1.0), M.Heartbeat)
            assert not link.board_silent
            link.stop_heartbeat()
            assert not link.heartbeat_running
    finally:
        a.shutdown()
        b.shutdown()


def test_host_arm_reads_the_epoch_and_retries_with_it():
    a, b = _bus_pair("identity-arm")
    board = CanBoard(b)
    try:
        with L.CanLink(a, node_id=1) as link:
            board.target.epoch = 77
            link.arm(timeout=1.0, retries=1)
            assert board.target.calls[-1] == ("arm",) and link.heartbeat_running
            link.disarm(timeout=1.0, retries=1)
            # the arm the host would retry (same epoch) after the disarm: refused
            with pytest.raises(L.CommandRefused) as ei:
                link.request(M.Arm(epoch=77), timeout=1.0, retries=1)
            assert ei.value.reason_name == "stale_epoch"
    finally:
        board.close()
        a.shutdown()
        b.shutdown()
