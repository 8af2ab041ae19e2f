"""One port, one owner, any number of tools: the local hub a serial link serves on its port.

The first tool that opens a serial device (:class:`host.link.clients.SerialLink`) takes it
exclusively (an ``flock``) and serves a hub on a Unix socket in a directory only its user
can enter (``$TMPDIR/upright-UID/``, one socket per device, named from the device's real
path; a path past the 107 bytes a Unix socket address holds, under a deep ``$TMPDIR``, is bound
and reached through the directory's descriptor).  A later upright tool that finds the port locked attaches to that socket instead of
failing, so ``upright board status`` works while ``upright board arm``, ``log`` or the
dashboard runs.  A process that is not an upright tool (mpremote, a terminal) gets the lock's
"port busy" with the holder's PID.

What travels on the socket is the serial framing itself (COBS frames with a sequence
number), so an attached tool is an ordinary :class:`SerialLink` on a socket.  The owner:

* forwards a tool's frames to the board with sequence numbers of its own link (one counter
  for the owner and every tool: no two requests in flight share one), and remembers which
  tool sent which request;
* hands the board's answer to a request to the tool that asked, with the tool's own
  sequence number restored -- and to nobody else; the answers to the owner's own requests
  stay with the owner;
* copies every other frame (heartbeats, telemetry, the board's periodic frames, with the
  board's own sequence numbers, so a recording tool counts losses exactly) to every tool;
* reads the port on behalf of the tools while it is attached to some and nobody in the
  owner reads (at most every 10 ms).

A tool that stops reading for a second is dropped; when the owner exits, the tools' links
report the lost link.  Linux only (``/proc``, Unix sockets); elsewhere the port is simply
exclusive.
"""

from __future__ import annotations

import errno
import hashlib
import os
import select
import socket
import struct
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from host.link import messages as M

__all__ = ["hub_path", "port_holders", "SocketPort", "attach", "PortHub"]

#: seconds a request waits for its answer in the hub's books
PENDING_S = 5.0
#: seconds a tool may block the hub's write before it is dropped
CLIENT_WRITE_S = 1.0
#: the hub's poll period (s): how often it reads the port for its tools when the owner does not
PUMP_S = 0.01


def _sock_dir(create: bool = True) -> Path | None:
    d = Path(tempfile.gettempdir()) / f"upright-{os.getuid()}"
    try:
        if create:
            d.mkdir(mode=0o700, exist_ok=True)
        st = d.stat()
    except OSError:
        return None
    # only a directory of our own that nobody else can enter holds a socket that commands a board
    if st.st_uid != os.getuid() or st.st_mode & 0o077:
        return None
    return d


#: the longest path a Unix socket address holds (``sun_path``, 108 bytes with its NUL on Linux)
SUN_PATH_MAX = 107


def _sock_call(call: Any, path: Path) -> None:
    """``call`` (a socket's ``bind`` or ``connect``) on ``path``, however long ``$TMPDIR`` is.

    A path longer than :data:`SUN_PATH_MAX` bytes (a deep ``$TMPDIR``: a test's temporary
    directory) goes through the directory's descriptor, ``/proc/self/fd/N/NAME``, which
    Linux resolves to the same file.
    """
    if len(os.fsencode(str(path))) <= SUN_PATH_MAX:
        call(str(path))
        return
    fd = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
    try:
        call(f"/proc/self/fd/{fd}/{path.name}")
    finally:
        os.close(fd)


def _drop_dir(d: Path) -> None:
    # the last hub leaves no directory behind (others keep it: rmdir fails on a directory with sockets)
    try:
        d.rmdir()
    except OSError:
        pass


def hub_path(port: str, create: bool = True) -> Path | None:
    """The hub socket of a device (None: no safe place for one; ``create=False``: only look, the
    private directory is not made)."""
    d = _sock_dir(create)
    if d is None:
        return None
    key = hashlib.sha1(os.path.realpath(port).encode()).hexdigest()[:16]
    return d / f"port-{key}.sock"


def _command_of(pid: int) -> str:
    # a process's command line, shortened to ``upright ...`` for our own tools
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            argv = [a.decode(errors="replace") for a in fh.read().split(b"\0") if a]
    except OSError:
        return "?"
    for i, a in enumerate(argv):
        if a == "host.cli.main" or os.path.basename(a) == "upright":
            return " ".join(["upright", *argv[i + 1:]])
    return " ".join(argv) or "?"


def port_holders(path: str) -> list[tuple[int, str]]:
    """Processes holding the device ``path``: the holder of its exclusive lock (``/proc/locks``,
    what :class:`host.link.clients.SerialLink` takes), else every process with it open
    (``/proc/*/fd``).

    Returns
    -------
    list of (int, str)
        ``(pid, command line)``; empty where ``/proc`` says nothing (not Linux, no access).
    """
    try:
        st = os.stat(path)
    except OSError:
        return []
    me = os.getpid()
    key = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    pids: list[int] = []
    try:
        with open("/proc/locks") as fh:
            for line in fh:
                parts = line.split()
                # "1: FLOCK  ADVISORY  WRITE 12440 00:1a:3 0 EOF"
                if len(parts) >= 6 and parts[1] == "FLOCK" and parts[5] == key and parts[4].isdigit():
                    pid = int(parts[4])
                    if pid != me and pid not in pids:
                        pids.append(pid)
    except OSError:
        pass
    if not pids:
        real = os.path.realpath(path)
        try:
            procs = [d for d in os.listdir("/proc") if d.isdigit() and int(d) != me]
        except OSError:
            procs = []
        for d in procs:
            try:
                fds = os.listdir(f"/proc/{d}/fd")
            except OSError:
                continue
            for fd in fds:
                try:
                    if os.readlink(f"/proc/{d}/fd/{fd}") == real:
                        pids.append(int(d))
                        break
                except OSError:
                    continue
    return [(pid, _command_of(pid)) for pid in pids]


# ------------------------------------------------------------------ the tool's side
class SocketPort:
    """The pyserial surface :class:`host.link.clients.SerialLink` uses, over a connected Unix socket."""

    def __init__(self, sock: socket.socket, port: str) -> None:
        self._sock = sock
        self.port = port
        sock.setblocking(False)
        self.timeout: float | None = 0.0
        self.is_open = True

    def fileno(self) -> int:
        return self._sock.fileno()

    @property
    def in_waiting(self) -> int:
        import fcntl
        import termios

        return struct.unpack("i", fcntl.ioctl(self._sock.fileno(), termios.FIONREAD, b"\0\0\0\0"))[0]

    def read(self, size: int = 1) -> bytes:
        t = self.timeout
        if t:
            select.select([self._sock], [], [], t)
        try:
            data = self._sock.recv(max(1, size))
        except (BlockingIOError, InterruptedError):
            return b""
        if not data:
            raise OSError(errno.EPIPE, f"the tool that owns {self.port} closed it (its hub is gone)")
        return data

    def write(self, data: bytes) -> int:
        view = memoryview(bytes(data))
        deadline = time.monotonic() + 5.0
        while view:
            try:
                n = self._sock.send(view)
            except (BlockingIOError, InterruptedError):
                if time.monotonic() > deadline:
                    raise OSError(errno.ETIMEDOUT, f"the hub of {self.port} does not take frames") from None
                select.select([], [self._sock], [], 0.1)
                continue
            view = view[n:]
        return len(data)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if self.is_open:
            self.is_open = False
            self._sock.close()


def attach(port: str) -> SocketPort | None:
    """Connect to the hub of the tool that holds ``port``; None when there is none."""
    path = hub_path(port, create=False)
    if path is None or not path.exists():
        return None
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.settimeout(1.0)
        _sock_call(s.connect, path)
    except OSError:
        s.close()
        return None
    return SocketPort(s, port)


# ------------------------------------------------------------------ the owner's side
def _request_key(msg: M.Message) -> tuple[str, int, int | None]:
    # what answers this message: (reply name, id it acknowledges, parameter index)
    if msg.NAME == "request":
        cls = M.MESSAGES.get(getattr(msg, "msg_id"))
        return (cls.NAME if cls else "ack", msg.ID, None)
    if msg.NAME in ("param_get", "param_set"):
        return ("param_value", msg.ID, getattr(msg, "index"))
    return ("ack", msg.ID, None)


def _answers(msg: M.Message, key: tuple[str, int, int | None]) -> bool:
    reply, mid, index = key
    if msg.NAME == "nack":
        return getattr(msg, "msg_id") == mid
    if msg.NAME == "ack":
        return reply == "ack" and getattr(msg, "msg_id") == mid
    if msg.NAME == "param_value":
        return reply == "param_value" and getattr(msg, "index") == index
    return msg.NAME == reply


class _Client:
    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        sock.setblocking(False)
        self.dec = M.SerialStreamDecoder()
        self.lock = threading.Lock()
        self.alive = True

    def send(self, data: bytes) -> None:
        with self.lock:
            if not self.alive:
                return
            view = memoryview(data)
            deadline = time.monotonic() + CLIENT_WRITE_S
            try:
                while view:
                    try:
                        n = self.sock.send(view)
                    except (BlockingIOError, InterruptedError):
                        if time.monotonic() > deadline:
                            raise OSError(errno.ETIMEDOUT, "tool does not read") from None
                        select.select([], [self.sock], [], 0.05)
                        continue
                    view = view[n:]
            except OSError:
                self.alive = False
                self.sock.close()


class PortHub:
    """The hub the owner of a port serves (see the module doc).

    Parameters
    ----------
    link : host.link.clients.SerialLink
        The owner's open link: its :meth:`send` numbers the tools' frames, its ``_ingest``
        calls :meth:`dispatch`.
    port : str
        The device.
    """

    def __init__(self, link: Any, port: str) -> None:
        path = hub_path(port)
        if path is None:
            raise OSError(errno.EACCES, "no private directory for the hub socket")
        self.link = link
        self.port = port
        self.path = path
        try:
            path.unlink()  # a stale socket of a tool that died: we hold the lock now
        except FileNotFoundError:
            pass
        self._srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            _sock_call(self._srv.bind, path)
            self._srv.listen(8)
        except OSError:
            self._srv.close()
            _drop_dir(path.parent)
            raise
        self._srv.setblocking(False)
        # close() wakes the thread through this pipe: without tools it sleeps in select
        self._wake_r, self._wake_w = os.pipe()
        self._lock = threading.Lock()
        self.clients: list[_Client] = []
        # seq -> (client or None for the owner, the client's seq, reply key, time sent)
        self._pending: dict[int, tuple[_Client | None, int, tuple[str, int, int | None], float]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True, name="upright-port-hub")
        self._thread.start()

    # ---- books ----
    def note_sent(self, msg: M.Message, seq: int, tag: tuple[_Client, int] | None) -> None:
        """A frame is going to the board with ``seq`` (called under the link's write lock)."""
        if tag is None and msg.NAME == "host_heartbeat":
            return  # never answered
        now = time.monotonic()
        with self._lock:
            if len(self._pending) > 64:
                for s in [s for s, v in self._pending.items() if now - v[3] > PENDING_S]:
                    del self._pending[s]
            client, cseq = tag if tag is not None else (None, 0)
            self._pending[seq] = (client, cseq, _request_key(msg), now)

    def dispatch(self, got: list[tuple[M.Message, int | None]]) -> list[tuple[M.Message, int | None]]:
        """Route what the owner's link received; returns what the owner keeps."""
        keep: list[tuple[M.Message, int | None]] = []
        out: list[tuple[_Client | None, bytes]] = []
        now = time.monotonic()
        with self._lock:
            for msg, seq in got:
                p = self._pending.get(seq) if seq is not None else None
                if p is not None and now - p[3] <= PENDING_S and _answers(msg, p[2]):
                    del self._pending[seq]
                    if p[0] is None:
                        keep.append((msg, seq))  # the owner's own answer: nobody else's business
                    else:
                        out.append((p[0], M.encode_serial(msg, p[1])))
                    continue
                keep.append((msg, seq))
                if self.clients:
                    out.append((None, M.encode_serial(msg, 0 if seq is None else seq)))
            clients = list(self.clients)
        for target, data in out:
            for c in ([target] if target is not None else clients):
                c.send(data)
        return keep

    # ---- the hub's thread ----
    def _loop(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                self.clients = [c for c in self.clients if c.alive]
                socks = [c.sock for c in self.clients]
            try:
                r = select.select([self._wake_r, self._srv, *socks], [], [], PUMP_S if socks else None)[0]
            except (OSError, ValueError):
                r = []
                if self._stop.is_set():
                    return
            for s in r:
                if s is self._wake_r:
                    continue
                if s is self._srv:
                    self._accept()
                else:
                    self._from_client(s)
            if self.clients:
                self._pump()

    def _accept(self) -> None:
        try:
            s, _ = self._srv.accept()
        except OSError:
            return
        with self._lock:
            self.clients.append(_Client(s))

    def _from_client(self, s: socket.socket) -> None:
        c = next((c for c in self.clients if c.sock is s), None)
        if c is None:
            return
        try:
            data = s.recv(4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            with c.lock:
                c.alive = False
                s.close()
            return
        for msg, seq in c.dec.feed(data):
            if msg.DIRECTION != "to_board":
                continue
            try:
                self.link.send(msg, _tag=(c, seq))
            except Exception:  # noqa: BLE001 - the owner's link is gone: the tools learn it from the socket
                self._stop.set()
                return

    def _pump(self) -> None:
        # read the port for the tools when the owner does not (its reads dispatch too)
        lk = self.link
        if lk._rx_lock.acquire(blocking=False):
            try:
                got = lk._recv_internal(0)
            except Exception:  # noqa: BLE001 - the owner sees the same error on its next read
                return
            finally:
                lk._rx_lock.release()
            lk._ingest(got)

    def close(self) -> None:
        """Stop serving: the tools' links report the lost link; the socket file is removed."""
        self._stop.set()
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=2)
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass
        try:
            self._srv.close()
        except OSError:
            pass
        try:
            self.path.unlink()
        except OSError:
            pass
        _drop_dir(self.path.parent)
        with self._lock:
            for c in self.clients:
                with c.lock:
                    c.alive = False
                    try:
                        c.sock.close()
                    except OSError:
                        pass
            self.clients = []
