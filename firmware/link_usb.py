# The Pico's own USB serial (CDC, the port mpremote uses) as the host link's byte stream
# (board.LINK = "usb"): the surface of machine.UART that link_serial.SerialLink uses (any,
# readinto, write) and the one main_hil.HilMain uses (wait, any, readinto(buf, n),
# write(buf, n)), on sys.stdin.buffer / sys.stdout.buffer.
#
# While it is open, Ctrl-C (0x03, a byte COBS frames carry) is an ordinary byte
# (micropython.kbd_intr(-1)), so the REPL cannot be reached by Ctrl-C.  Ways back to it:
# the MODE repl command (`upright board --port /dev/ttyACM0 mode repl`: close() restores
# Ctrl-C and main() returns), or a reset and Ctrl-C within board.USB_REPL_MS of boot
# (main.py waits that long before it opens the link: `mpremote` sends Ctrl-C when it
# connects, so reset the board and run it at once).
#
# stdin's readinto waits for all n bytes, so one byte is read per ready poll (bounded: the
# caller reads what any()/wait() reported).  Nothing allocates after __init__.

from .hilport import HilPort


class UsbStream(HilPort):
    def __init__(self):
        import select
        import sys
        import micropython
        self._kbd = micropython.kbd_intr
        self._rd = sys.stdin.buffer.readinto
        self._wr = sys.stdout.buffer.write
        self._poll = select.poll()
        self._poll.register(sys.stdin, select.POLLIN)
        self._ipoll = self._poll.ipoll
        for _ in self._ipoll(0):  # the first ipoll allocates its result tuple
            pass
        self._b = bytearray(1)
        self._buf = None
        self._views = None
        self.hup = False
        self._kbd(-1)

    def close(self):
        # the REPL's Ctrl-C back (MODE repl)
        self._kbd(3)

    def wait(self, timeout_ms):
        for _ in self._ipoll(timeout_ms):
            return True
        return False

    def any(self):
        # 0 when nothing waits, else 64: the count is not known, and readinto() below never
        # waits (it stops when no byte is ready), so asking for more is safe
        for _ in self._ipoll(0):
            return 64
        return 0

    def readinto(self, buf, nbytes=-1):
        if nbytes < 0:
            nbytes = len(buf)
        b = self._b
        i = 0
        while i < nbytes:
            if not self.any():
                break
            self._rd(b, 1)
            buf[i] = b[0]
            i += 1
        return i

    def write(self, buf, nbytes=-1):
        if nbytes < 0:
            return self._wr(buf)
        if buf is not self._buf:
            self._slices(buf)
        return self._wr(self._views[nbytes])

    def _slices(self, buf):
        mv = memoryview(buf)
        self._views = [mv[:i] for i in range(len(buf) + 1)]
        self._buf = buf
