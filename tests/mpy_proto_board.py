# A protocol "board" for the MicroPython unix port (test helper, not firmware):
# firmware decoder + dispatcher + encoder on a tty, with host.link.standin as the target.
#   micropython tests/mpy_proto_board.py TTY serial|can SECONDS
# Prints "ready" once the port is open, then serves until SECONDS pass or a
# DISARM arrives after a SET_REFERENCE of exactly 424242 um (host.link.standin.QUIT_REF);
# prints counters at exit.
import sys
import time
import micropython
from firmware import canframe, codec, commands, framing
from firmware.uart_unix import UnixUART
from host.link.standin import StandIn


def main():
    path, mode, secs = sys.argv[1], sys.argv[2], int(sys.argv[3])
    uart = UnixUART(path)
    layout = codec.Layout()
    tg = StandIn()
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
