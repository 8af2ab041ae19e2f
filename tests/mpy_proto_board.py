# A protocol "board" for the MicroPython unix port (test helper, not firmware):
# firmware decoder + dispatcher + encoder on a tty, with a small in-script target.
#   micropython tests/mpy_proto_board.py TTY serial|can SECONDS
# Prints "ready" once the port is open, then serves until SECONDS pass or a
# DISARM arrives after a SET_REFERENCE of exactly 424242 um; prints counters at exit.
import sys
import time
import micropython
from firmware import canframe, codec, commands, framing
from firmware import msgtable as T
from firmware.uart_unix import UnixUART


class Target:
    def __init__(self):
        self.state = 0
        self.faults = 0
        self.ref = 0
        self.params = [p[5] for p in T.PARAMS]
        self.gains_n = 0
        self.quit = False

    def cmd_arm(self):
        self.state = 1
        return 0

    def cmd_disarm(self):
        self.state = 0
        if self.ref == 424242:
            self.quit = True
        return 0

    def cmd_clear_faults(self):
        self.faults = 0
        return 0

    def cmd_set_reference(self, x_um):
        self.ref = x_um
        return 0

    def param_get(self, i):
        return self.params[i]

    def param_set(self, i, v):
        self.params[i] = v
        return 0

    def gains_apply(self, buf, n):
        self.gains_n = n
        return 0

    def fill_heartbeat(self, a):
        a[0] = self.state
        a[1] = self.faults
        a[2] = 9
        a[3] = 0x3FFFFFFF

    def fill_telemetry(self, a):
        for i in range(8):
            a[i] = i - 4

    def fill_timing(self, a):
        a[0] = 1
        a[1] = 2
        a[2] = 3
        a[3] = 65535


def main():
    path, mode, secs = sys.argv[1], sys.argv[2], int(sys.argv[3])
    uart = UnixUART(path)
    layout = codec.Layout()
    tg = Target()
    if mode == "serial":
        dec = framing.Decoder(layout)
        tx = framing.SerialTx(framing.Encoder(layout), uart.write)
        pbuf = dec.buf
        poff = 2
    else:
        dec = canframe.SerialCanDecoder(layout, 1)
        tx = canframe.SerialCanTx(canframe.SerialCanWriter(layout, 1), uart.write, time.ticks_ms)
        pbuf = dec.data
        poff = 0
    disp = commands.Dispatcher(tg, layout, tx)
    rx = bytearray(64)
    print("ready")
    t0 = time.ticks_ms()
    locked = 0
    while not tg.quit and time.ticks_diff(time.ticks_ms(), t0) < secs * 1000:
        if not uart.wait(20):
            continue
        n = uart.readinto(rx)
        # the whole receive/dispatch/reply path runs with the heap locked
        micropython.heap_lock()
        for i in range(n):
            m = dec.feed(rx[i])
            if m >= 0:
                disp.handle(m, dec.seq if mode == "serial" else 0, pbuf, poff)
                locked += 1
        micropython.heap_unlock()
    print("handled", disp.n_handled, "refused", disp.n_refused, "locked", locked, "ref", tg.ref, "gains", tg.gains_n)


main()
