"""The emulated Pico's ports on pseudo-terminals: its UART0 and its USB CDC, each a port any tool opens.

:class:`PtyBridge` runs an :class:`~host.boards.rp2040.board.EmulatedBoard` with ``main.py`` (the
board as after ``make flash``) and copies bytes between its UART0 and the master end of a pty:
what a tool writes to the slave (``/dev/pts/N``) goes onto the board's RX line at the line's
byte timing, what the board sends comes out of the slave.  A second pty carries the board's
USB CDC port (the Pico's micro-USB, ``/dev/ttyACM0`` on a real one): MicroPython's REPL (what
``mpremote`` opens) with the default ``LINK = "uart"``, or the host link itself with
``link="usb"`` (``LINK = "usb"`` in ``firmware/board.py``: ``main.main(link="usb")``), where
``mode repl`` hands the port back to the REPL.  On its own the bridge holds the
sensors still (the pendulum upright at the potentiometer's offset, the encoder at 0); the
virtual robot (:mod:`host.hil.virtual_robot`, ``upright emulate rp2040 --pty``) drives them
between :meth:`PtyBridge.run` calls from the simulated robot instead.

The emulation runs at most as fast as real time (in practice slower: about 0.1 board
seconds per wall second with the firmware's busy-waiting loop), so a tool's timeouts, counted
on the wall clock, are generous in board time.

The bridge keeps its own handle on the slave end, so a tool may close the port and another
open it again; what the board sends while nobody reads is dropped once the pty's buffer is
full (as a USB-serial adapter with no host does).
"""

from __future__ import annotations

import errno
import os
import select
import termios
import time
import tty
from pathlib import Path
from typing import Callable

from host.boards.rp2040.board import CYCLES_PER_US, FIRMWARE, EmulatedBoard, StepResult

__all__ = ["PtyBridge"]


class PtyBridge:
    """An emulated board whose UART0 is bridged to a new pty (see the module docstring).

    Parameters
    ----------
    bundle_dir : Path, optional
        Firmware bundle (default: built into a temporary directory).
    firmware : Path
        The MicroPython image.
    chunk_us : float
        Board time run between two looks at the pty.
    adc : int, optional
        ADC0 input held during the run (default: ``sensors.pot_offset`` of ``sim/robot.toml``,
        the pendulum upright).
    link : {"uart", "usb"}
        The board's host link: UART0 (the default board's) or its USB CDC port.

    Attributes
    ----------
    port : str
        The slave path (``/dev/pts/N``) of the host link (UART0's or USB's pty).
    uart_port, usb_port : str
        The ptys of UART0 and of the USB CDC port.
    board : EmulatedBoard
        The running board.
    """

    def __init__(self, bundle_dir: Path | None = None, *, firmware: Path = FIRMWARE, chunk_us: float = 2000.0,
                 adc: int | None = None, link: str = "uart") -> None:
        self.chunk_us = float(chunk_us)
        self.link = link
        self._master, self._slave = os.openpty()
        self._usb_master, self._usb_slave = os.openpty()
        self.uart_port = os.ttyname(self._slave)
        self.usb_port = os.ttyname(self._usb_slave)
        self.port = self.usb_port if link == "usb" else self.uart_port
        try:
            for fd in (self._slave, self._usb_slave):
                tty.setraw(fd)  # no echo, no line editing before a tool sets its own mode
            for fd in (self._master, self._usb_master):
                os.set_blocking(fd, False)
            if adc is None:
                from sim.params import load_params

                adc = int(round(load_params().pot_offset))
            # the angle held from power-on: the firmware's first reads see the pendulum upright
            self.board = EmulatedBoard(bundle_dir, firmware=firmware, main=True, link=link, adc=int(adc))
        except BaseException:
            self._close_fds()
            raise
        self.rx_bytes = 0
        self.tx_bytes = 0
        self.tx_dropped = 0

    def _close_fds(self) -> None:
        for fd in (self._master, self._slave, self._usb_master, self._usb_slave):
            try:
                os.close(fd)
            except OSError:
                pass
        self._master = self._slave = self._usb_master = self._usb_slave = -1

    def close(self) -> None:
        """Stop the board and remove the pty."""
        board = getattr(self, "board", None)
        if board is not None:
            board.close()
            self.board = None  # type: ignore[assignment]
        self._close_fds()

    def __enter__(self) -> "PtyBridge":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _write(self, data: bytes, master: int | None = None, slave: int | None = None) -> None:
        master = self._master if master is None else master
        slave = self._slave if slave is None else slave
        view = memoryview(data)
        while view:
            try:
                n = os.write(master, view)
            except BlockingIOError:
                # nobody reads the port: drop what waits there (stale for the next tool)
                termios.tcflush(slave, termios.TCIFLUSH)
                try:
                    n = os.write(master, view)
                except BlockingIOError:
                    self.tx_dropped += len(view)
                    return
            view = view[n:]
        self.tx_bytes += len(data)

    @staticmethod
    def _read(master: int) -> bytes:
        try:
            return os.read(master, 4096)
        except BlockingIOError:
            return b""
        except OSError as exc:  # pragma: no cover - EIO when no slave is open (we hold one)
            if exc.errno != errno.EIO:
                raise
            return b""

    def run(self, us: float) -> StepResult:
        """Copy what a tool wrote onto the board's RX line, run ``us`` of board time, copy the
        board's output to the pty (the same for the USB CDC port and its pty); returns the run's
        :class:`StepResult` (its ``uart_tx`` and ``usb_tx`` already delivered).  The pins are whatever the caller set (the virtual robot sets them between
        runs: :mod:`host.hil.virtual_robot`)."""
        data = self._read(self._master)
        if data:
            self.rx_bytes += len(data)
            self.board.uart_write(data)
        data = self._read(self._usb_master)
        if data:
            self.board.usb_write(data)
        r = self.board.run(us)
        if r.uart_tx:
            self._write(r.uart_tx)
        if r.usb_tx:
            self._write(r.usb_tx, self._usb_master, self._usb_slave)
        self.board.drop_usb_output()  # delivered to the pty: no backlog on the host side
        return r

    def step(self) -> None:
        """:meth:`run` for ``chunk_us``."""
        self.run(self.chunk_us)

    def serve(self, stop: Callable[[], bool] = lambda: False) -> None:
        """Run until ``stop()`` is true, never faster than real time (the sensors held).

        Raises
        ------
        BoardError
            The board raised or stopped (quoting its last output).
        """
        t0 = time.monotonic()
        c0 = self.board.cycles
        while not stop():
            self.step()
            ahead = (self.board.cycles - c0) / (CYCLES_PER_US * 1e6) - (time.monotonic() - t0)
            if ahead > 0:
                select.select([self._master, self._usb_master], [], [], ahead)
