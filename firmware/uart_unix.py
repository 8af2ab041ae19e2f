# A machine.UART-like byte stream for the MicroPython unix port, over a tty path
# (the slave end of a pty, or a real serial device such as /dev/ttyUSB0).
#
# The HIL main uses it where a board uses machine.UART: same small surface
# (any, readinto, write, close) plus wait(timeout_ms) to block until a byte arrives.
#
# Allocation (measured under the unix port with micropython.heap_lock(), see
# tests/test_hil_vport.py): readinto(), write(), any() and wait() allocate nothing
# after construction.  What makes that hold:
# - the tty is put in raw mode (termios.setraw) with VMIN = 0, VTIME = 0, so a read
#   returns at once with whatever is buffered (0 bytes = nothing there).  With the
#   default VMIN = 1, MicroPython's readinto() loops until the buffer is full;
# - select.poll().ipoll() yields a callee-owned tuple (allocated on the first call,
#   made here) and allocates nothing after;
# - FileIO.readinto(buf, n) and FileIO.write(buf, off, n) fill/take preallocated
#   buffers directly, no slicing (a memoryview slice would allocate);
# - the open() and the termios calls (which build lists) happen once, here.
# Errors (a closed peer: EIO on a pty whose other end went away) are not raised
# from the loop methods: readinto() returns 0 and sets self.error to the errno.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from .hilport import HilPort

_VMIN = const(6)
_VTIME = const(5)
_CC = const(6)


class UnixUART(HilPort):
    # path: tty device path (str) or an already-open file descriptor (int).
    # baudrate: applied with termios when the port knows the rate (ignored on a pty).
    def __init__(self, path, baudrate=115200):
        import select
        import termios
        self._f = open(path, "r+b")
        self._fd = self._f.fileno()
        termios.setraw(self._fd)
        attr = termios.tcgetattr(self._fd)
        cc = attr[_CC]
        cc[_VMIN] = 0
        cc[_VTIME] = 0
        speed = getattr(termios, "B%d" % baudrate, None)
        if speed is not None:
            attr[4] = speed
            attr[5] = speed
        termios.tcsetattr(self._fd, termios.TCSANOW, attr)
        self._poll = select.poll()
        self._poll.register(self._f, select.POLLIN)
        self._pin = select.POLLIN
        self._bad = select.POLLERR | select.POLLHUP
        # ipoll() allocates its result tuple on first use: do it now
        for _ in self._poll.ipoll(0):
            pass
        self.error = 0
        # set once the peer has hung up (POLLHUP/POLLERR seen by wait())
        self.hup = False
        self.rx_bytes = 0
        self.tx_bytes = 0

    def fileno(self):
        return self._fd

    def wait(self, timeout_ms):
        # block until a byte can be read (True) or timeout_ms passes (False);
        # -1 waits forever.  A hung-up peer also returns True (readinto then says 0)
        # and sets self.hup.
        for ev in self._poll.ipoll(timeout_ms):
            if ev[1] & self._bad:
                self.hup = True
            return (ev[1] & (self._pin | self._bad)) != 0
        return False

    def any(self):
        # 1 if at least one byte is waiting, else 0 (a tty does not say how many)
        for ev in self._poll.ipoll(0):
            if ev[1] & self._pin:
                return 1
        return 0

    def readinto(self, buf, nbytes=-1):
        # read what is there, at most nbytes (default len(buf)), never blocking;
        # returns the count (0 = nothing, or an error: see self.error)
        if nbytes < 0:
            nbytes = len(buf)
        try:
            n = self._f.readinto(buf, nbytes)
        except OSError as e:
            self.error = e.errno
            return 0
        if n is None:
            return 0
        self.rx_bytes += n
        return n

    def write(self, buf, nbytes=-1, off=0):
        # write nbytes of buf starting at off (default: all of buf); returns the count
        if nbytes < 0:
            nbytes = len(buf) - off
        try:
            n = self._f.write(buf, off, nbytes)
        except OSError as e:
            self.error = e.errno
            return 0
        self.tx_bytes += n
        return n

    def close(self):
        try:
            self._poll.unregister(self._f)
        except Exception:
            pass
        self._f.close()
