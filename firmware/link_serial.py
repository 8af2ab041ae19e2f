# Host link of a board in normal (not HIL) operation: COBS serial frames on a UART
# (framing.py), commands dispatched to the app (commands.py), telemetry every
# telem_div ticks and a heartbeat every heartbeat_ms.  poll() is called by App.run()
# once per tick after the control step; it allocates nothing.  Every valid frame feeds
# the app's command watchdog.
#
# uart: machine.UART-like with any() and readinto(buf, n); write(buf) takes a whole
# buffer, so one memoryview per frame length is made here, once.

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

_RX = const(64)


class SerialLink:
    def __init__(self, uart, app):
        self.uart = uart
        self.app = app
        layout = codec.Layout()
        table = crc16.make_table()
        self.dec = framing.Decoder(layout, table)
        enc = framing.Encoder(layout, table)
        mv = memoryview(enc.out)
        self._views = [mv[:k] for k in range(len(enc.out) + 1)]
        self.tx = framing.SerialTx(enc, self._write)
        self.disp = commands.Dispatcher(app, layout, self.tx, table)
        self.rx = bytearray(_RX)
        self.tseq = 0
        self._telem_left = 0
        self._hb_ticks = 0
        self._feed = self.dec.feed
        self._uart_write = uart.write
        self._readinto = uart.readinto
        self._any = uart.any

    def _write(self, buf, n):
        self._uart_write(self._views[n])

    def poll(self):
        app = self.app
        if self._any():
            n = self._readinto(self.rx, _RX)
            if n:
                rx = self.rx
                feed = self._feed
                dec = self.dec
                for i in range(n):
                    mid = feed(rx[i])
                    if mid >= 0:
                        app.feed_watchdog()
                        self.disp.handle(mid, dec.seq, dec.buf, 2)
        div = app.param_get(T.P_TELEM_DIV)
        if div > 0:
            self._telem_left -= 1
            if self._telem_left <= 0:
                self._telem_left = div
                self.tseq = (self.tseq + 1) & 0xFF
                self.disp.send_telemetry(self.tseq)
        hb = app.param_get(T.P_HEARTBEAT_MS)
        if hb > 0:
            self._hb_ticks += app.period_us
            if self._hb_ticks >= hb * 1000:
                self._hb_ticks = 0
                self.tseq = (self.tseq + 1) & 0xFF
                self.disp.send_heartbeat(self.tseq)
