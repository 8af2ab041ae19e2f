"""The virtual serial port: pty + MicroPython unix port + firmware/uart_unix.py (real interpreter)."""

from __future__ import annotations

import os

import pytest

from host.boards.vport import PTMX, BoardExited, PortError, VirtualBoard, open_can, open_serial, slave_of

ECHO = r"""
import gc, micropython
from firmware.uart_unix import UnixUART


def loop(u, buf, out):
    # a function, so that its variables are locals (a new global would grow a dict)
    n = 0
    frames = 0
    while True:
        if not u.wait(5000):
            break
        k = u.readinto(buf)
        if k == 0:
            break
        u.write(buf, k)
        n += k
        frames += 1
    out[0] = n
    out[1] = frames


u = UnixUART(%r)
buf = bytearray(64)
r = [0, 0]
gc.collect()
micropython.heap_lock()
try:
    loop(u, buf, r)
finally:
    micropython.heap_unlock()
print("echoed", r[0], "frames", r[1])
"""

# every byte value, including the ones a cooked tty would eat or translate
PAYLOAD = bytes(range(256))


def test_uart_unix_echo_is_transparent_and_allocation_free() -> None:
    ser = open_serial(PTMX, timeout=5.0)
    try:
        board = VirtualBoard(slave_of(ser.fileno()), code=ECHO % "SLAVE")
        board.cmd[-1] = ECHO % board.slave
        with board:
            got = 0
            for i in range(200):
                msg = PAYLOAD[i % 200: i % 200 + 50] or b"\x01"
                ser.write(msg)
                back = ser.read(len(msg))
                assert back == msg
                got += len(msg)
            ser.close()  # the firmware sees the hang-up (EIO) and leaves its loop
            board.proc.wait(timeout=10)
            out = board.output()
        assert board.returncode == 0, out
        fields = out.split()
        assert fields[0] == "echoed" and int(fields[1]) == got, out
        # heap_lock was held for the whole loop: a single allocation would have raised
        # MemoryError and a non-zero exit status
        assert int(fields[3]) == 200, out
    finally:
        ser.close()


def test_board_exits_when_host_closes_the_master() -> None:
    ser = open_serial(PTMX, timeout=1.0)
    board = VirtualBoard(slave_of(ser.fileno()), code=ECHO % "SLAVE")
    board.cmd[-1] = ECHO % board.slave
    with board:
        ser.close()
        board.proc.wait(timeout=10)
    assert board.returncode == 0


def test_bad_serial_port_is_one_line_error() -> None:
    with pytest.raises(PortError) as ei:
        open_serial("/dev/does-not-exist-upright")
    msg = str(ei.value)
    assert "/dev/does-not-exist-upright" in msg and "\n" not in msg


def test_bad_can_channel_is_one_line_error() -> None:
    with pytest.raises(PortError) as ei:
        open_can("/dev/does-not-exist-upright", interface="serial")
    assert "\n" not in str(ei.value)
    with pytest.raises(PortError):
        open_can("nope0", interface="no-such-interface")


def test_slave_of_rejects_non_pty() -> None:
    fd = os.open("/dev/null", os.O_RDWR)
    try:
        with pytest.raises(PortError):
            slave_of(fd)
    finally:
        os.close(fd)


def test_board_start_failure_names_the_error() -> None:
    ser = open_serial(PTMX, timeout=1.0)
    try:
        with pytest.raises(BoardExited) as ei:
            VirtualBoard(slave_of(ser.fileno()), code="raise ValueError('boom at start')").start()
        assert "boom at start" in str(ei.value)
    finally:
        ser.close()


BOARD_UART = r"""
import gc, micropython, io
from firmware import main_hil, framing, codec, msgtable as T
from array import array

class FakeUART(io.IOBase):
    # machine.UART-like: any(), readinto(buf, n), write(buf); pollable via ioctl
    def __init__(self, data):
        self.rx = data; self.pos = 0; self.out = bytearray(8192); self.n = 0
    def any(self): return len(self.rx) - self.pos
    def readinto(self, buf, n):
        k = len(self.rx) - self.pos
        if k > n: k = n
        if k > 8: k = 8
        for i in range(k): buf[i] = self.rx[self.pos + i]
        self.pos += k
        return k
    def write(self, b):
        for i in range(len(b)):
            self.out[self.n + i] = b[i]
        self.n += len(b)
        return len(b)
    def ioctl(self, req, arg):
        return 0

lay = codec.Layout(); enc = framing.Encoder(lay)
data = bytearray()
v = array('i', [0, 2048, 0, 0])
for t in range(200):
    v[0] = t
    n = enc.encode(T.HIL_SENSOR, t, v, 0)
    data += enc.out[:n]
u = FakeUART(bytes(data))
b = main_hil.BoardUART(u)
m = main_hil.HilMain(b, 'serial', 'lockstep', 1)
m.app.params[T.P_HEARTBEAT_MS] = 0
# warm-up: the first frame makes BoardUART's slices of the transmit buffer
while m.n_steps < 1:
    m._drain(True)
gc.collect()
def loop(m, u):
    while u.pos < len(u.rx):
        m._drain(True)
micropython.heap_lock()
loop(m, u)
micropython.heap_unlock()
# decode what the firmware answered
dec = framing.Decoder(lay); vals = array('i', [0]*4); ticks = []
for i in range(u.n):
    mid = dec.feed(u.out[i])
    if mid == T.HIL_ACTUATOR:
        lay.unpack(mid, dec.buf, 2, vals, 0); ticks.append(vals[0])
print(m.n_steps, ticks == list(range(200)))
"""


def test_board_uart_adapter_runs_the_lockstep_loop_allocation_free() -> None:
    # a machine.UART-like object (any, readinto(buf, n), write(buf) only) wrapped in
    # main_hil.BoardUART, 200 sensor frames, the loop heap-locked: every tick answered
    from host.boards.mpyrun import run_unix

    out = run_unix(BOARD_UART, timeout=60)
    assert out.split() == ["200", "True"], out


def test_boot_counter_persists_across_a_restart(tmp_path) -> None:
    from host.link.clients import SerialLink

    boot = str(tmp_path / "boot.txt")
    link = SerialLink(PTMX)
    try:
        board = VirtualBoard(slave_of(link._ser.fileno()), boot_file=boot)
        with board:
            b0 = link.query("heartbeat").boot
            board.proc.kill()
            board.stop()
            board.start()
            b1 = link.query("heartbeat", timeout=0.5, retries=3).boot
        assert b1 == (b0 + 1) & 0xFF
    finally:
        link.close()


def test_boot_counter_on_by_default_and_can_be_off() -> None:
    from host.link.clients import SerialLink

    link = SerialLink(PTMX)
    try:
        board = VirtualBoard(slave_of(link._ser.fileno()))
        assert board.boot_file is not None
        boots = []
        with board:
            for _ in range(3):
                boots.append(link.query("heartbeat", timeout=0.5, retries=3).boot)
                board.proc.kill()
                board.stop()
                board.start()
        assert boots == [1, 2, 3]  # incremented on every start, from 0 without a file (firmware.main.boot_count)
        off = VirtualBoard(slave_of(link._ser.fileno()), boot_counter=False)
        assert off.boot_file is None
        with pytest.raises(ValueError):
            VirtualBoard(slave_of(link._ser.fileno()), boot_counter=False, boot_file="x")
    finally:
        link.close()


EMITTER_SCRIPT = r"""
from firmware import board, main_hil
from firmware.hilport import HilPort
class U(HilPort):
    def write(self, b, n=None):
        return len(b)
    def readinto(self, b, n=None):
        return 0
    def wait(self, ms):
        return False
    def any(self):
        return 0
m = main_hil.HilMain(U())
print(m.app.emitter, board.EMITTER, type(m.app.sensors).__name__, type(m.pacer).__name__,
      m.tx.enc._fast is not None, m.disp.crc30 is not None)
m = main_hil.HilMain(U(), config={'emitter': 'bytecode'})
print(m.app.emitter, type(m.app.sensors).__name__, type(m.pacer).__name__)
"""


def test_hil_runs_the_boards_emitter_unless_told_otherwise() -> None:
    # the unix-port HIL (and the board's HIL mode, main.py's _hil) runs what the robot runs:
    # firmware/board.py EMITTER's builds of the step, the pacer, the frame encoder, the CRC
    from host.boards.mpyrun import run_unix

    first, second = run_unix(EMITTER_SCRIPT, timeout=60).strip().splitlines()
    assert first.split() == ["viper", "viper", "SensorsV", "PacerV", "True", "True"]
    assert second.split() == ["bytecode", "Sensors", "Pacer"]
