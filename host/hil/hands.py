"""The virtual robot's hands on a Unix socket: what a person does to the robot, on request.

:class:`HandsServer` listens at :func:`hands_path` of the robot's port (derived from the port, so
a tool given only ``--port`` finds it; a real robot has none) and hands each request to the
robot (:meth:`host.hil.virtual_robot.VirtualRobot.handle`); :class:`Hands` is the client
(``upright board calibrate --robot auto``, the tests), :func:`find_hands` finds the robot behind
a port.  One JSON object per line each way: ``{"do": ACTION, ...}`` -> ``{"ok": true, ...}`` or
``{"ok": false, "error": ...}``; the actions are in :mod:`host.hil.virtual_robot`.
"""

from __future__ import annotations

import json
import os
import re
import select
import socket
import stat
import time
from pathlib import Path
from typing import Any, Callable

__all__ = ["HandsError", "HandsServer", "Hands", "hands_path", "find_hands"]


class HandsError(RuntimeError):
    """The virtual robot's hands: no answer, a refused action, a lost connection."""


# ---------------------------------------------------------------------- the socket
def hands_path(port: str) -> Path:
    """Where the virtual robot behind ``port`` listens: a Unix socket in ``$XDG_RUNTIME_DIR``
    (else ``/tmp``) named after the port's real path and the user (``upright-robot-1000-dev_pts_7.sock``)."""
    real = os.path.realpath(port) if port.startswith("/") else port  # can:INTERFACE:CHANNEL as it is
    tag = re.sub(r"[^A-Za-z0-9]+", "_", real.strip("/")) or "port"
    base = os.environ.get("XDG_RUNTIME_DIR") or ""
    if not base or not os.path.isdir(base):
        base = "/tmp"
    return Path(base) / f"upright-robot-{os.getuid()}-{tag}.sock"


class HandsServer:
    """The robot's hands on a Unix socket (module docstring), polled from the serve loop.

    Parameters
    ----------
    path : Path
        Socket path (a stale socket there is replaced).
    robot : host.hil.virtual_robot.VirtualRobot
        Who does the actions (``handle(request, done)``).
    """

    def __init__(self, path: Path, robot: Any) -> None:
        self.path = Path(path)
        self.robot = robot
        try:
            if stat.S_ISSOCK(os.lstat(self.path).st_mode):
                self.path.unlink()  # a stale socket (a robot that was killed): this port is ours now
        except FileNotFoundError:
            pass
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self.sock.bind(str(self.path))
            os.chmod(self.path, 0o600)
            self.sock.listen(4)
            self.sock.setblocking(False)
        except BaseException:
            self.sock.close()
            raise
        self.conns: dict[socket.socket, bytearray] = {}

    def poll(self) -> None:
        """Accept connections, read requests, hand them to the robot (never blocks)."""
        try:
            ready = select.select([self.sock, *self.conns], [], [], 0)[0]
        except (OSError, ValueError):
            return
        for s in ready:
            if s is self.sock:
                try:
                    c, _ = self.sock.accept()
                    c.setblocking(False)
                    self.conns[c] = bytearray()
                except OSError:
                    pass
                continue
            try:
                data = s.recv(4096)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                data = b""
            if not data:
                self._drop(s)
                continue
            buf = self.conns[s]
            buf += data
            while b"\n" in buf:
                line, _, rest = bytes(buf).partition(b"\n")
                buf[:] = rest
                self._request(s, line)

    def _request(self, conn: socket.socket, line: bytes) -> None:
        def done(answer: dict[str, Any]) -> None:
            if conn not in self.conns:
                return
            try:
                conn.setblocking(True)
                conn.sendall((json.dumps(answer) + "\n").encode())
                conn.setblocking(False)
            except OSError:
                self._drop(conn)

        if not line.strip():
            return
        try:
            req = json.loads(line)
            if not isinstance(req, dict):
                raise ValueError("a request is a JSON object")
        except ValueError as exc:
            done({"ok": False, "error": f"bad request: {exc}"})
            return
        self.robot.handle(req, done)

    def _drop(self, conn: socket.socket) -> None:
        self.conns.pop(conn, None)
        try:
            conn.close()
        except OSError:
            pass

    def close(self) -> None:
        """Close every connection and remove the socket file."""
        for c in list(self.conns):
            self._drop(c)
        self.sock.close()
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass


# ---------------------------------------------------------------------- the client
class Hands:
    """A client of the virtual robot's hands (:class:`HandsServer`).

    Parameters
    ----------
    path : str or Path
        The socket.
    timeout : float
        Wall seconds an answer may take (the emulator runs at about 0.1-0.2x real time).

    Raises
    ------
    HandsError
        Nothing listens there.
    """

    def __init__(self, path: str | Path, *, timeout: float = 300.0) -> None:
        self.path = Path(path)
        self.timeout = float(timeout)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self.sock.connect(str(self.path))
        except OSError as exc:
            self.sock.close()
            raise HandsError(f"no virtual robot listens on {self.path}: {exc}") from exc
        self._buf = b""
        self.info = self.do("hello")

    def do(self, action: str, idle: Callable[[], None] | None = None, **kw: Any) -> dict[str, Any]:
        """Ask for one action and wait for its answer, calling ``idle()`` about every 20 ms meanwhile
        (a tool keeps its host heartbeat going there).

        Raises
        ------
        HandsError
            The robot refused (its error message), did not answer within :attr:`timeout`, or went away.
        """
        try:
            self.sock.sendall((json.dumps({"do": action, **kw}) + "\n").encode())
        except OSError as exc:
            raise HandsError(f"the virtual robot on {self.path} went away: {exc}") from exc
        t_end = time.monotonic() + self.timeout
        while b"\n" not in self._buf:
            left = t_end - time.monotonic()
            if left <= 0:
                raise HandsError(f"the virtual robot did not do {action!r} within {self.timeout:g} s")
            if select.select([self.sock], [], [], min(0.02, left))[0]:
                try:
                    chunk = self.sock.recv(4096)
                except OSError as exc:
                    raise HandsError(f"the virtual robot on {self.path} went away: {exc}") from exc
                if not chunk:
                    raise HandsError(f"the virtual robot on {self.path} went away (it was stopped?)")
                self._buf += chunk
            elif idle is not None:
                idle()
        line, _, self._buf = self._buf.partition(b"\n")
        ans = json.loads(line)
        if not ans.get("ok"):
            raise HandsError(f"the virtual robot refused {action!r}: {ans.get('error')}")
        return ans

    def close(self) -> None:
        """Hang up."""
        self.sock.close()

    def __enter__(self) -> "Hands":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def find_hands(port: str, **kw: Any) -> Hands | None:
    """The virtual robot behind ``port``, or ``None`` (a real robot: no socket, or a stale one)."""
    path = hands_path(port)
    if not path.exists():
        return None
    try:
        h = Hands(path, **kw)
    except HandsError:
        return None
    same = os.path.realpath if port.startswith("/") else (lambda v: v)
    if h.info.get("port") and same(str(h.info["port"])) != same(port):
        h.close()
        return None
    return h
