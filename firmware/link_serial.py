# Host link of a board in normal (not HIL) operation: COBS serial frames on a UART
# (framing.py), commands dispatched to the app (commands.py), telemetry and heartbeats
# paced by pacer.Pacer (as in the HIL main).  poll() is called by App.run() once per
# tick after the control step; it allocates nothing.  Only HOST_HEARTBEAT and
# SET_REFERENCE frames feed the app's link watchdog (commands.py): a monitor polling the
# board does not keep a dead controlling host alive.
#
# uart: machine.UART-like with any() (bytes waiting; a port may say 1 when there are
# more) and readinto(buf, n).  Only bytes any() reported are read: rp2's readinto waits
# for all n bytes (up to an inter-character timeout of >= 1 ms at 1 Mbaud), a stall of
# half a loop period.  At most _RX bytes per tick (bounded time); the rest waits in the
# UART's receive buffer (HalPico.uart() makes it large) for the next tick.  write(buf)
# takes a whole buffer, so one memoryview per frame length is made here, once.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from . import codec
from . import commands
from . import crc16
from . import framing
from . import msgtable as T
from .pacer import Pacer

_RX = const(64)


class ModeSwitch(Exception):
    # MODE hil/repl was ACKed: raised out of poll() (so out of App.run()) once the ACK is
    # written; main.py hands the link to the mode asked for (SerialLink.mode)
    pass


class SerialLink:
    def __init__(self, uart, app):
        self.uart = uart
        self.app = app
        layout = codec.Layout()
        table = crc16.make_table()
        self.dec = framing.Decoder(layout, table)
        # frames packed/CRC'd/stuffed by the app's emitter (viper on the board: fastframe.py)
        enc = framing.Encoder(layout, table, getattr(app, "emitter", "bytecode"))
        mv = memoryview(enc.out)
        self._views = [mv[:k] for k in range(len(enc.out) + 1)]
        self.tx = framing.SerialTx(enc, self._write)
        self.disp = commands.Dispatcher(app, layout, self.tx, table)
        self.disp.dec = self.dec
        self.pacer = Pacer(app, self.disp)
        self._tick = self.pacer.tick
        # MODE: the mode asked for (-1: stay in robot mode); the exception made now (the
        # heap is locked when it is raised)
        self.mode = -1
        self._switch = ModeSwitch()
        self.disp.on_mode = self._on_mode
        self.rx = bytearray(_RX)
        self._scan = self.dec.scan
        self._uart_write = uart.write
        self._readinto = uart.readinto
        self._any = uart.any

    def _write(self, buf, n):
        self._uart_write(self._views[n])

    def poll(self):
        # idle (nothing received): one any() and the pacer
        n = self._any()
        if n:
            self._receive(n)
            if self.mode >= 0:
                raise self._switch
        self._tick()

    def _on_mode(self, m):
        # MODE (commands.py: motor off, m valid): robot is this mode already
        if m != T.MODE_ROBOT:
            self.mode = m
        return T.OK

    def _receive(self, n):
        # at most _RX bytes this tick, n of them waiting now
        rx = self.rx
        left = _RX
        while True:
            if n > left:
                n = left
            n = self._readinto(rx, n)
            if not n:
                break
            left -= n
            self._frames(n)
            if left <= 0:
                break
            n = self._any()
            if not n:
                break

    def _frames(self, n):
        # decode rx[0:n]; every complete valid frame is dispatched
        dec = self.dec
        scan = self._scan
        rx = self.rx
        i = 0
        while i < n:
            mid = scan(rx, i, n)
            i = dec.next
            if mid >= 0:
                self.disp.handle(mid, dec.seq, dec.buf, 2)
