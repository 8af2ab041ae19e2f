"""A serial link on a bare file descriptor: what a new host process gets after the old one crashed."""

from __future__ import annotations

from host.link.clients import SerialLink

__all__ = ["FdPort", "serial_link_on_fd"]


class FdPort:
    """The pyserial surface :class:`host.link.clients.SerialLink` uses, over an open file descriptor.

    A host process that crashes leaves the line (the board's USB port, here the pty master
    held by the test) as it was; a new host process gets the line again.  ``FdPort`` lets a
    link be made on such an inherited or kept descriptor (see :func:`serial_link_on_fd`).

    Parameters
    ----------
    fd : int
        Open descriptor (not closed by :meth:`close` unless ``own=True``).
    own : bool
        Close ``fd`` on :meth:`close`.
    """

    def __init__(self, fd: int, *, own: bool = False) -> None:
        self.fd = int(fd)
        self.own = bool(own)
        self.timeout: float | None = 0.0
        self.is_open = True

    def fileno(self) -> int:
        return self.fd

    @property
    def in_waiting(self) -> int:
        import fcntl
        import struct
        import termios

        return struct.unpack("i", fcntl.ioctl(self.fd, termios.FIONREAD, b"\0\0\0\0"))[0]

    def read(self, size: int = 1) -> bytes:
        import os
        import select

        t = self.timeout
        r, _, _ = select.select([self.fd], [], [], t)
        if not r:
            return b""
        try:
            return os.read(self.fd, size)
        except BlockingIOError:
            return b""

    def write(self, data: bytes) -> int:
        import os
        import select

        view = memoryview(bytes(data))
        while view:
            select.select([], [self.fd], [], 1.0)
            try:
                n = os.write(self.fd, view)
            except BlockingIOError:
                continue
            view = view[n:]
        return len(data)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        import os

        if self.is_open and self.own:
            os.close(self.fd)
        self.is_open = False


def serial_link_on_fd(fd: int, *, own: bool = False) -> SerialLink:
    """A :class:`host.link.clients.SerialLink` on an already open descriptor (see :class:`FdPort`)."""
    link = SerialLink("loop://")
    link._ser.close()
    link._ser = FdPort(fd, own=own)
    link.url = f"fd:{fd}"
    return link
