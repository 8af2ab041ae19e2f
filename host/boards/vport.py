"""A virtual serial port with the firmware on the other end: a pty and the MicroPython unix port.

The host opens the pty *master* exactly as it opens a real board's port -- pyserial's
``serial_for_url("/dev/ptmx")`` or python-can's ``can.Bus(interface="serial",
channel="/dev/ptmx")`` -- because opening ``/dev/ptmx`` creates a fresh pty pair.
:func:`slave_of` unlocks that pair and names its slave end (``/dev/pts/N``), and
:class:`VirtualBoard` starts the firmware's HIL main (:mod:`firmware.main_hil`) under
``.venv/bin/micropython`` with that path as its UART.  So the host's link code is the
same for ``--virtual`` and ``--port /dev/ttyACM0``; only who is on the other end differs.

Shutdown is clean: :meth:`VirtualBoard.stop` asks the firmware to stop (it exits when its
UART hangs up, i.e. when the host closes the master), then terminates and finally kills
it if it does not go, and always reaps the process.  Bad ports and CAN channels become
one-line :class:`PortError` messages, never tracebacks (:func:`open_serial`,
:func:`open_can`).

A probed board (``VirtualBoard(..., probe=True)``) runs the unchanged HIL main inside a small
wrapper that holds ``micropython.heap_lock()`` for the whole lockstep run and prints, at exit,
the heap in use before and after and the firmware decoder's drop counters -- the board
exposes neither over the link; :meth:`VirtualBoard.probe_report` reads them.
"""

from __future__ import annotations

import fcntl
import math
import os
import re
import signal
import struct
import subprocess
import time
from pathlib import Path
from typing import Any

from host.boards.mpyrun import ROOT, micropython_exe

__all__ = [
    "PTMX",
    "PortError",
    "BoardExited",
    "slave_of",
    "open_serial",
    "open_can",
    "firmware_command",
    "probe_code",
    "set_realtime",
    "steal_seconds",
    "VirtualBoard",
]

PTMX = "/dev/ptmx"
"""Opening this path creates a new pty pair; the opener holds the master end."""

# linux/asm-generic ioctls (not exported by Python's termios module)
_TIOCSPTLCK = 0x40045431  # unlock the slave
_TIOCGPTN = 0x80045430  # number N of /dev/pts/N


class PortError(OSError):
    """A serial port or CAN channel cannot be opened or used (one-line message)."""


class BoardExited(PortError):
    """The virtual board's MicroPython process ended (its stderr tail is in the message)."""


def slave_of(master_fd: int) -> str:
    """Unlock the pty whose master is ``master_fd`` and return its slave path.

    Parameters
    ----------
    master_fd : int
        File descriptor from opening :data:`PTMX`.

    Returns
    -------
    str
        ``/dev/pts/N``.

    Raises
    ------
    PortError
        If ``master_fd`` is not a pty master.
    """
    try:
        fcntl.ioctl(master_fd, _TIOCSPTLCK, struct.pack("i", 0))
        n = struct.unpack("i", fcntl.ioctl(master_fd, _TIOCGPTN, struct.pack("i", 0)))[0]
    except OSError as exc:
        raise PortError(f"fd {master_fd} is not a pty master: {exc.strerror}") from exc
    return f"/dev/pts/{n}"


def open_serial(port: str, *, baudrate: int | None = None, timeout: float | None = 1.0) -> Any:
    """Open a serial port (or pyserial URL) for a link, with a one-line error.

    Parameters
    ----------
    port : str
        Device path, pyserial URL, or :data:`PTMX` for a new virtual port.
    baudrate : int, optional
        Line rate (ignored by ptys); default the board's (``firmware/board.py`` ``UART_BAUD``).
    timeout : float or None
        Read timeout (s).

    Returns
    -------
    serial.Serial

    Raises
    ------
    PortError
        If the port does not exist or cannot be opened.
    """
    import serial

    if baudrate is None:
        from firmware.board import UART_BAUD as baudrate
    try:
        return serial.serial_for_url(port, baudrate=int(baudrate), timeout=timeout)
    except (serial.SerialException, ValueError, OSError) as exc:
        raise PortError(f"cannot open serial port {port!r}: {_short(exc)}") from exc


def open_can(channel: str, *, interface: str = "serial", **kwargs: Any) -> Any:
    """Open a python-can bus, with a one-line error.

    Parameters
    ----------
    channel : str
        Channel of the interface (``/dev/ptmx`` for a virtual port with ``interface="serial"``,
        ``can0`` with ``socketcan``, ...).
    interface : str
        python-can interface name.
    **kwargs
        Passed to :class:`can.Bus` (e.g. ``bitrate``).

    Raises
    ------
    PortError
        If python-can cannot open the channel.
    """
    import can

    try:
        return can.Bus(interface=interface, channel=channel, **kwargs)
    except (can.CanError, ValueError, OSError, ImportError, TypeError) as exc:
        raise PortError(f"cannot open CAN channel {channel!r} ({interface}): {_short(exc)}") from exc


def _short(exc: BaseException) -> str:
    msg = str(exc).strip().splitlines()
    return msg[0] if msg else type(exc).__name__


def set_realtime(priority: int | None, pid: int = 0) -> bool:
    """Put a process (or, with ``pid=0``, the calling thread) under ``SCHED_FIFO``.

    Parameters
    ----------
    priority : int or None
        1..99; ``None`` or 0 restores ``SCHED_OTHER``.
    pid : int
        Process id (0: the calling thread).

    Returns
    -------
    bool
        True if the policy was applied (False where not permitted or not supported).
    """
    try:
        if priority:
            os.sched_setscheduler(pid, os.SCHED_FIFO, os.sched_param(int(priority)))
        else:
            os.sched_setscheduler(pid, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        return False
    return True


def steal_seconds() -> float:
    """CPU time the hypervisor has taken from this virtual machine so far, all CPUs (s).

    The ``steal`` column of ``/proc/stat`` (Linux; in clock ticks): time a vCPU was ready
    to run but the host ran something else.  Nothing inside the VM can prevent it, not
    even ``SCHED_FIFO``; real-time statistics are read against it.  ``nan`` where the
    kernel does not report it.
    """
    try:
        with open("/proc/stat") as fh:
            fields = fh.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return math.nan


def firmware_command(port: str, *, link: str = "serial", mode: str = "lockstep", node: int = 1,
                     heapsize: str | None = None, heap_lock: bool = False,
                     boot_file: str | None = None) -> list[str]:
    """The command line that runs :func:`firmware.main_hil.main` under the unix port.

    Parameters
    ----------
    port : str
        Slave tty path the firmware opens as its UART.
    link : {"serial", "can"}
        Framing on the byte stream.
    mode : {"lockstep", "realtime"}
        Loop mode.
    node : int
        CAN node id.
    heapsize : str, optional
        ``-X heapsize=`` value.
    heap_lock : bool
        Run the firmware's loop under ``micropython.heap_lock()``: one allocation ends
        the run with ``MemoryError`` (the allocation-free proof of the HIL tests).
    boot_file : str, optional
        File where the firmware keeps its boot counter (incremented at every start and
        reported in ``heartbeat.boot``); ``None``: no counter (boot stays 0).
    """
    if link not in ("serial", "can"):
        raise ValueError(f"link must be 'serial' or 'can', got {link!r}")
    if mode not in ("lockstep", "realtime"):
        raise ValueError(f"mode must be 'lockstep' or 'realtime', got {mode!r}")
    code = (
        "import sys\nfrom firmware import main_hil\n"
        f"sys.exit(main_hil.main({port!r}, link={link!r}, mode={mode!r}, node={int(node)}, "
        f"heap_lock={bool(heap_lock)}, boot_file={boot_file!r}))\n"
    )
    cmd = [micropython_exe()]
    if heapsize:
        cmd += ["-X", f"heapsize={heapsize}"]
    return cmd + ["-c", code]


_PROBE = r"""
import sys, gc, micropython
from firmware import main_hil
from firmware.uart_unix import UnixUART


def go():
    u = UnixUART(%(port)r)
    m = main_hil.HilMain(u, %(link)r, %(mode)r, %(node)d)
    gc.collect()
    a0 = gc.mem_alloc()
    lock = %(lock)r
    if lock:
        micropython.heap_lock()
    else:
        gc.disable()
    try:
        rc = m.run()
    finally:
        if lock:
            micropython.heap_unlock()
    a1 = gc.mem_alloc()
    d = m.dec
    out = "UPRIGHT-PROBE alloc0=%%d alloc1=%%d locked=%%d steps=%%d frames=%%d" %% (a0, a1, lock, m.n_steps, m.n_frames)
    for k in ("n_ok", "n_crc", "n_length", "n_unknown", "n_overrun", "n_framing", "n_other"):
        if hasattr(d, k):
            out += " %%s=%%d" %% (k, getattr(d, k))
    out += " refused=%%d handled=%%d" %% (m.disp.n_refused, m.disp.n_handled)
    print(out)
    return rc


sys.exit(go())
"""

_PROBE_RE = re.compile(r"UPRIGHT-PROBE (.*)")


def probe_code(port: str, *, link: str = "serial", mode: str = "lockstep", node: int = 1) -> str:
    """MicroPython source of the probed HIL main (see the module docstring).

    The firmware is the unchanged :class:`firmware.main_hil.HilMain`; the wrapper holds
    ``micropython.heap_lock()`` for the whole run in lockstep mode -- one allocation anywhere
    in the loop, the decoder or the command handler ends the firmware with ``MemoryError``
    -- and, in real-time mode, disables the GC instead and reports the growth.  At exit it
    prints ``gc.mem_alloc()`` before and after the run (``alloc0``, ``alloc1``, ``locked``),
    the steps and frames handled, the decoder's drop counters and the commands refused and
    handled, on one line that :meth:`VirtualBoard.probe_report` parses.
    """
    if link not in ("serial", "can"):
        raise ValueError(f"link must be 'serial' or 'can', got {link!r}")
    if mode not in ("lockstep", "realtime"):
        raise ValueError(f"mode must be 'lockstep' or 'realtime', got {mode!r}")
    return _PROBE % {"port": port, "link": link, "mode": mode, "node": int(node), "lock": mode == "lockstep"}


class VirtualBoard:
    """The firmware's HIL main running under the MicroPython unix port on a pty slave.

    Parameters
    ----------
    slave : str
        Slave tty path (from :func:`slave_of`).
    link : {"serial", "can"}
        Framing the firmware speaks.
    mode : {"lockstep", "realtime"}
        Loop mode.
    node : int
        CAN node id.
    heapsize : str, optional
        MicroPython heap size (``"512k"``).
    startup_timeout : float
        Seconds to wait for the firmware to open the slave.
    code : str, optional
        MicroPython source to run instead of the HIL main (tests and tools); it must open
        ``slave`` itself.
    heap_lock, boot_file
        See :func:`firmware_command`.  ``boot_file=None`` (default): the board keeps its
        boot counter in a file of its own temporary directory (removed with the object),
        so every :meth:`stop`/:meth:`start` of this board reports a new
        ``heartbeat.boot`` (0, 1, 2, ...) as a real board's flash file does.
    boot_counter : bool
        False: no boot counter at all (``heartbeat.boot`` stays 0); ``boot_file`` must
        then be None.
    probe : bool
        Run the probed HIL main (:func:`probe_code`): heap and decoder counters reported at
        exit, read with :meth:`probe_report`.  Not with ``code``.
    rt_priority : int, optional
        Run the interpreter under the ``SCHED_FIFO`` real-time policy at this priority
        (1..99), as a board's loop owns its CPU; a real-time-mode firmware sharing a busy
        2-core machine with the host and other jobs otherwise misses deadlines whenever
        the OS schedules something else.  Silently ignored where not permitted (the run
        then shows the overruns, which is the truth about that machine).

    Examples
    --------
    >>> ser = open_serial(PTMX)                               # doctest: +SKIP
    >>> with VirtualBoard(slave_of(ser.fileno())) as board:   # doctest: +SKIP
    ...     ...  # talk to the firmware over ``ser``
    """

    def __init__(self, slave: str, *, link: str = "serial", mode: str = "lockstep", node: int = 1,
                 heapsize: str | None = None, startup_timeout: float = 10.0, code: str | None = None,
                 rt_priority: int | None = None, heap_lock: bool = False, boot_file: str | None = None,
                 boot_counter: bool = True, probe: bool = False) -> None:
        import tempfile

        if probe and code is not None:
            raise ValueError("probe=True runs the probed HIL main: give no code")
        if probe:
            code = probe_code(slave, link=link, mode=mode, node=node)
        self.probe = bool(probe)
        self.slave = slave
        self._boot_dir: tempfile.TemporaryDirectory[str] | None = None
        if not boot_counter:
            if boot_file is not None:
                raise ValueError("boot_file given with boot_counter=False")
        elif boot_file is None:
            self._boot_dir = tempfile.TemporaryDirectory(prefix="upright-board-")
            boot_file = str(Path(self._boot_dir.name) / "boot_count")
        self.boot_file = boot_file
        self.rt_priority = rt_priority
        self.realtime_policy = False
        self.cmd = firmware_command(slave, link=link, mode=mode, node=node, heapsize=heapsize, heap_lock=heap_lock,
                                    boot_file=boot_file)
        if code is not None:
            self.cmd = [*self.cmd[:-1], code]
        self.startup_timeout = float(startup_timeout)
        self.proc: subprocess.Popen[bytes] | None = None
        self._err_path: Path | None = None
        self._err_fh: Any = None
        self._last_output = ""

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "VirtualBoard":
        """Start the interpreter and wait until the firmware has opened its UART.

        Raises
        ------
        BoardExited
            If MicroPython exits during start-up (its error is in the message).
        """
        import tempfile

        env = dict(os.environ, MICROPYPATH=f"{ROOT}:.frozen")
        fd, name = tempfile.mkstemp(prefix="upright-fw-", suffix=".log")
        self._err_path = Path(name)
        self._err_fh = os.fdopen(fd, "w+b")
        self.proc = subprocess.Popen(self.cmd, cwd=ROOT, env=env, stdin=subprocess.DEVNULL,
                                     stdout=self._err_fh, stderr=subprocess.STDOUT)
        if self.rt_priority is not None:
            self.realtime_policy = set_realtime(self.rt_priority, self.proc.pid)
        deadline = time.monotonic() + self.startup_timeout
        while not self._slave_opened():
            if self.proc.poll() is not None:
                raise BoardExited(f"firmware exited at start-up: {self.output_tail()}")
            if time.monotonic() > deadline:
                self.stop()
                raise BoardExited(f"firmware did not open {self.slave} within {self.startup_timeout:g} s")
            time.sleep(0.005)
        return self

    def _slave_opened(self) -> bool:
        # the firmware has the slave open once one of its fds points at it
        assert self.proc is not None
        fd_dir = Path(f"/proc/{self.proc.pid}/fd")
        try:
            for entry in fd_dir.iterdir():
                try:
                    if os.readlink(entry) == self.slave:
                        return True
                except OSError:
                    continue
        except OSError:
            return False
        return False

    @property
    def alive(self) -> bool:
        """True while the interpreter runs."""
        return self.proc is not None and self.proc.poll() is None

    @property
    def returncode(self) -> int | None:
        """Exit status once it has ended."""
        return None if self.proc is None else self.proc.poll()

    def output(self) -> str:
        """Everything the firmware printed (stdout and stderr) so far."""
        if self._err_path is None or not self._err_path.exists():
            return self._last_output
        return self._err_path.read_bytes().decode("utf-8", "replace")

    def output_tail(self, lines: int = 3) -> str:
        """Last lines of the firmware's output, joined on one line."""
        tail = [s for s in self.output().strip().splitlines() if s.strip()][-lines:]
        return " | ".join(tail) if tail else f"(no output, exit status {self.returncode})"

    def probe_report(self) -> dict[str, int] | None:
        """The probed firmware's exit report (``probe=True``, after it ended), or ``None``
        if it did not report (it crashed: e.g. ``MemoryError`` under the heap lock -- its
        output tail says why, :meth:`output_tail`)."""
        m = _PROBE_RE.search(self.output())
        if m is None:
            return None
        return {k: int(v) for k, v in (kv.split("=") for kv in m.group(1).split())}

    def check(self) -> None:
        """Raise :class:`BoardExited` if the firmware has ended."""
        if self.proc is not None and self.proc.poll() is not None:
            raise BoardExited(f"firmware exited with status {self.proc.returncode}: {self.output_tail()}")

    def stop(self, timeout: float = 2.0) -> int | None:
        """Stop the firmware: wait for it to exit (after the host closed the master), then
        SIGTERM, then SIGKILL; always reap it and remove its log.

        Returns
        -------
        int or None
            Its exit status.
        """
        proc = self.proc
        if proc is not None:
            for sig in (None, signal.SIGTERM, signal.SIGKILL):
                if proc.poll() is not None:
                    break
                if sig is not None:
                    try:
                        proc.send_signal(sig)
                    except ProcessLookupError:
                        break
                try:
                    proc.wait(timeout=timeout if sig is None else 1.0)
                except subprocess.TimeoutExpired:
                    continue
        self._last_output = self.output()
        if self._err_fh is not None:
            self._err_fh.close()
            self._err_fh = None
        if self._err_path is not None:
            try:
                self._err_path.unlink()
            except OSError:
                pass
            self._err_path = None
        return None if proc is None else proc.returncode

    def __enter__(self) -> "VirtualBoard":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
