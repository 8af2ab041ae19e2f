"""Shared helpers of the protocol tests (not a test module)."""

from __future__ import annotations

from array import array

from hypothesis import strategies as st

from firmware import codec, framing
from firmware.commands import Target
from firmware import msgtable as T
from firmware.supervisor import ARMED, DISARMED, FAULT
from host.link import messages as M


def message_strategy(cls: type[M.Message] | None = None) -> st.SearchStrategy[M.Message]:
    """Any message of the table (or of one class) with arbitrary in-range raw fields."""
    if cls is None:
        return st.sampled_from(list(M.MESSAGES.values())).flatmap(message_strategy)
    kw = {}
    for f in cls.FIELDS:
        if f.is_raw:
            kw[f.name] = st.binary(min_size=f.size, max_size=f.size)
        else:
            lo, hi = f.bounds
            kw[f.name] = st.integers(lo, hi)
    return st.builds(cls, **kw)


def fw_small(f: M.Field, v: int) -> int:
    """What the firmware's unpack yields for a raw value (small-int rule)."""
    if f.fmt == "I":
        return v & 0x3FFFFFFF
    if f.fmt == "i":
        return max(-(2**30 - 1), min(2**30 - 1, v))
    return v


def fw_encode(msg: M.Message, seq: int) -> bytes:
    """Serial wire bytes produced by the firmware encoder (under CPython)."""
    layout = codec.Layout()
    enc = framing.Encoder(layout)
    vals = array("i", [0] * 8)
    for k, f in enumerate(msg.FIELDS):
        if not f.is_raw:
            vals[k] = getattr(msg, f.name) if f.fmt != "I" else getattr(msg, f.name) - (1 << 32 if getattr(msg, f.name) >= 1 << 31 else 0)
    off = 2
    for f in msg.FIELDS:
        if f.is_raw:
            enc.raw[off:off + f.size] = getattr(msg, f.name)
        off += f.size
    n = layout.pack(msg.ID, vals, 0, enc.raw, 2)
    return bytes(enc.out[: enc.frame(msg.ID, seq, n)])


def fw_decode_stream(data: bytes, block: int = 0) -> tuple[list[tuple[int, int, bytes]], dict[str, int]]:
    """Run the firmware decoder (CPython) over ``data``: frames and drop counters.

    ``block=0`` feeds byte by byte with ``feed``; otherwise ``scan`` over blocks of
    that many bytes (as a UART read would deliver them).
    """
    layout = codec.Layout()
    dec = framing.Decoder(layout)
    out = []
    if block:
        for s in range(0, len(data), block):
            chunk = bytearray(data[s:s + block])
            i = 0
            while i < len(chunk):
                m = dec.scan(chunk, i, len(chunk))
                assert i < dec.next <= len(chunk)
                i = dec.next
                if m >= 0:
                    out.append((m, dec.seq, bytes(dec.buf[2:2 + dec.plen])))
        return out, {"crc": dec.n_crc, "length": dec.n_length, "unknown": dec.n_unknown, "overrun": dec.n_overrun}
    for b in data:
        m = dec.feed(b)
        if m >= 0:
            out.append((m, dec.seq, bytes(dec.buf[2:2 + dec.plen])))
    return out, {"crc": dec.n_crc, "length": dec.n_length, "unknown": dec.n_unknown, "overrun": dec.n_overrun}


# ---------------------------------------------------------------- test doubles
class RecordingTarget(Target):
    """The firmware target interface as a recording test double (not the real app)."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []
        self.state = DISARMED
        self.faults = 0
        self.ref = 0
        self.params = [p[5] for p in T.PARAMS]
        self.gains: bytes | None = None
        self.gains_reason = 0
        self.telemetry = [1, -2, 3, -4, 5, -6, 7, 8]
        self.epoch = 0
        self.timing = [10, 20, 30, 0]

    def snapshot(self) -> tuple:
        return (self.state, self.faults, self.ref, tuple(self.params), self.gains)

    def cmd_arm(self) -> int:
        self.calls.append(("arm",))
        self.state = ARMED
        return T.OK

    def cmd_disarm(self) -> int:
        self.calls.append(("disarm",))
        self.state = DISARMED
        self.epoch = (self.epoch + 1) & 0xFF
        return T.OK

    def cmd_clear_faults(self) -> int:
        self.calls.append(("clear_faults",))
        self.faults = 0
        if self.state == FAULT:
            self.state = DISARMED
        return T.OK

    def cmd_set_reference(self, x_um: int) -> int:
        self.calls.append(("set_reference", x_um))
        self.ref = x_um
        return T.OK

    def param_get(self, index: int) -> int:
        return self.params[index]

    def param_set(self, index: int, value: int) -> int:
        self.calls.append(("param_set", index, value))
        self.params[index] = value
        return T.OK

    def gains_apply(self, buf, nbytes: int) -> int:
        self.calls.append(("gains_apply", nbytes))
        if self.gains_reason:
            return self.gains_reason
        self.gains = bytes(buf[:nbytes])
        return T.OK

    def fill_heartbeat(self, arr) -> None:
        arr[0], arr[1], arr[2], arr[3], arr[4], arr[5] = self.state, self.faults, 7, self.epoch, 0x5A, 1234

    def fill_telemetry(self, arr) -> None:
        for i, v in enumerate(self.telemetry):
            arr[i] = v

    def fill_timing(self, arr) -> None:
        for i, v in enumerate(self.timing):
            arr[i] = v


class RecordingSender:
    """Collects what the dispatcher sends, as host messages."""

    def __init__(self) -> None:
        from firmware import codec

        self.layout = codec.Layout()
        self.sent: list[tuple[M.Message, int]] = []

    def send(self, mid, seq, vals, voff) -> None:
        buf = bytearray(8)
        n = self.layout.pack(mid, vals, voff, buf, 0)
        self.sent.append((M.MESSAGES[mid].from_payload(bytes(buf[:n])), seq))


class PtyBridge:
    """Two pty pairs joined master-to-master by a thread: two tty paths that talk.

    Each end can be opened by pyserial, python-can's ``serial`` interface or any
    program (MicroPython) exactly like a USB serial device.
    """

    def __init__(self) -> None:
        import os
        import threading

        self._m1, s1 = os.openpty()
        self._m2, s2 = os.openpty()
        self.a, self.b = os.ttyname(s1), os.ttyname(s2)
        # keep the slave fds open (raw) so the ptys stay alive between opens
        import tty

        tty.setraw(s1)
        tty.setraw(s2)
        self._slaves = (s1, s2)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._pump, daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        import os
        import select

        pairs = {self._m1: self._m2, self._m2: self._m1}
        while not self._stop.is_set():
            r, _, _ = select.select(list(pairs), [], [], 0.02)
            for fd in r:
                try:
                    data = os.read(fd, 4096)
                except OSError:
                    continue
                if data:
                    os.write(pairs[fd], data)

    def close(self) -> None:
        import os

        self._stop.set()
        self._thread.join(timeout=2)
        for fd in (self._m1, self._m2, *self._slaves):
            try:
                os.close(fd)
            except OSError:
                pass


class SerialBoard:
    """A board peer on a byte stream: firmware decoder + dispatcher + encoder (CPython).

    ``read(n)``/``write(buf)`` are the transport's byte functions; the bytes written
    are produced by the firmware modules (serial COBS framing, or python-can serial
    CAN frames when ``can_node`` is given).
    """

    def __init__(self, read, write, can_node: int | None = None) -> None:
        import threading

        from firmware import canframe, codec, commands, framing

        self.target = RecordingTarget()
        layout = codec.Layout()
        if can_node is None:
            self.dec = framing.Decoder(layout)
            tx = framing.SerialTx(framing.Encoder(layout), lambda buf, n: write(bytes(buf[:n])))
        else:
            self.dec = canframe.SerialCanDecoder(layout, can_node)
            tx = canframe.SerialCanTx(canframe.SerialCanWriter(layout, can_node), lambda buf, n: write(bytes(buf[:n])), lambda: 0)
        self.disp = commands.Dispatcher(self.target, layout, tx)
        self._can = can_node is not None
        self._read = read
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            data = self._read(64)
            for b in data:
                m = self.dec.feed(b)
                if m >= 0:
                    if self._can:
                        self.disp.handle(m, 0, self.dec.data, 0)
                    else:
                        self.disp.handle(m, self.dec.seq, self.dec.buf, 2)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)


class CanBoard:
    """A board peer on a python-can bus: firmware dispatcher, payloads packed by firmware code."""

    def __init__(self, bus, node: int = 1) -> None:
        import threading

        import can

        from firmware import canframe, codec, commands

        layout = codec.Layout()
        self.target = RecordingTarget()
        data = bytearray(8)

        class Tx:
            def send(self, mid, seq, vals, voff):
                n = layout.pack(mid, vals, voff, data, 0)
                bus.send(can.Message(arbitration_id=canframe.can_id(node, mid), data=bytes(data[:n]), is_extended_id=False))

        self.disp = commands.Dispatcher(self.target, layout, Tx())
        self._bus, self._node, self._layout = bus, node, layout
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from firmware import canframe

        while not self._stop.is_set():
            f = self._bus.recv(0.02)
            if f is None or canframe.node_of(f.arbitration_id) != self._node:
                continue
            mid = canframe.msg_of(f.arbitration_id)
            if self._layout.plen[mid] == len(f.data):
                self.disp.handle(mid, 0, bytearray(f.data), 0)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
