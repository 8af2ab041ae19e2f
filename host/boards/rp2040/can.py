"""The emulated Pico on a CAN bus: its MCP2515 (modelled in ``mcp2515.mjs``) bridged to python-can.

The board's controller sits on SPI1 with the pins of ``firmware/board.py`` (``CAN_*``); the harness
models the chip at the register level and the bus at its bit timing (see ``mcp2515.mjs``).
:class:`CanBridge` carries frames between that bus and any python-can bus, in lock-step with
emulated time: before each run the frames other nodes put on the python-can bus enter the
emulated bus at the current board time (and then take their bit time there, arbitrating with the
board's own); after it, every frame the controller finished sending goes onto the python-can bus
with its emulated completion time as timestamp.  With python-can's ``virtual`` interface the host
tools (:class:`host.link.clients.CanLink`) run in the same process; ``udp_multicast`` reaches
other processes on the machine (``upright emulate rp2040 --can``, :meth:`CanBoard.serve`), and
``socketcan`` a ``vcan``/``can`` interface.  udp_multicast hands a process its own frames back
(multicast loopback, which the other processes on the machine need): the bridge drops those
echoes of the board's frames (:attr:`CanBridge.echoes`)::

    with CanBoard(channel="emu") as cb:                  # main.py with the CAN link
        link = CanLink(interface="virtual", channel="emu", node_id=1)
        link.send(...)
        cb.run(10_000)                                   # 10 ms of board time, frames both ways

:class:`CanBoard` is an :class:`~host.boards.rp2040.board.EmulatedBoard` proxy whose :meth:`run`
pumps the bridge, so code written for the board (the emulated HIL) runs over CAN unchanged.
"""

from __future__ import annotations

import json
import select
import time
from collections import deque
from pathlib import Path
from typing import Any, Callable

from host.boards.rp2040.board import CYCLES_PER_US, FIRMWARE, BoardError, EmulatedBoard, StepResult

__all__ = ["CanBridge", "CanBoard", "harness_args", "CAN_MAIN", "ECHOING", "UDP_LOCAL_GROUP"]

ECHOING = frozenset({"udp_multicast"})
"""python-can interfaces that deliver a bus's own frames back to it."""
UDP_LOCAL_GROUP = "ff11:7079:7468:6f6e:6465:6d6f:6d63:6173"
"""An interface-local IPv6 multicast group (scope 1: loopback only, never sent on a network) for
``udp_multicast`` -- python-can's default group with scope 5 (site) replaced by 1."""

CAN_MAIN = b"""# upright firmware entry, CAN link (host/boards/rp2040/can.py)
from firmware import main
main.main(link="can")
"""


def harness_args(*, xtal_hz: int | None = None, attach: bool = True) -> list[str]:
    """``harness.mjs`` options attaching an MCP2515 where ``firmware/board.py`` wires it.

    ``attach=False``: none (a board without its controller: SPI reads 0).
    """
    if not attach:
        return []
    from firmware import board as fb

    spec = {"spi": fb.CAN_SPI_ID, "cs": fb.CAN_CS_PIN, "int": fb.CAN_INT_PIN,
            "xtal": int(xtal_hz if xtal_hz is not None else fb.CAN_XTAL_HZ)}
    return ["--mcp2515", json.dumps(spec)]


class CanBridge:
    """Frames between an emulated board's MCP2515 and a python-can bus.

    Parameters
    ----------
    board : EmulatedBoard
        Started with :func:`harness_args`.
    bus : can.BusABC, optional
        The python-can side; otherwise ``can.Bus(interface=interface, channel=channel)``.
    channel, interface : str
        Used when ``bus`` is not given.
    log : bool
        Keep every frame (``self.frames``: ``(cycle, "tx"|"rx", id, data)``, tx = from the board).
    echo : bool, optional
        The bus hands back the frames it sends (default: for :data:`ECHOING` interfaces); those
        are dropped (counted in ``self.echoes``) instead of going back onto the emulated bus.
    """

    def __init__(self, board: EmulatedBoard, bus: Any = None, *, channel: str = "upright-emu",
                 interface: str = "virtual", log: bool = True, echo: bool | None = None) -> None:
        import can

        self._can = can
        self.board = board
        self._own = bus is None
        self.bus = bus if bus is not None else can.Bus(interface=interface, channel=channel)
        self.log = log
        self.frames: list[tuple[int, str, int, bytes]] = []
        self.n_to_board = 0
        self.n_from_board = 0
        self.echoes = 0
        if echo is None:
            echo = bus is None and interface in ECHOING
        # the board's frames sent and not yet seen coming back (bounded: a lost echo is forgotten)
        self._sent: deque[tuple[int, bytes]] | None = deque(maxlen=512) if echo else None
        # every run of the board pumps the bridge, also those exec() and the REPL make
        self._board_run = board.run
        board.run = self.run  # type: ignore[method-assign]

    def to_board(self) -> int:
        """Move the frames waiting on the python-can bus onto the emulated bus (now); returns the count."""
        out = []
        while True:
            m = self.bus.recv(0)
            if m is None:
                break
            if m.is_extended_id or m.is_remote_frame or m.is_error_frame:
                continue
            if self._sent is not None:
                key = (int(m.arbitration_id), bytes(m.data))
                if key in self._sent:  # our own frame handed back: the board sent it already
                    self._sent.remove(key)
                    self.echoes += 1
                    continue
            out.append([int(m.arbitration_id), bytes(m.data).hex()])
            if self.log:
                self.frames.append((self.board.cycles, "rx", int(m.arbitration_id), bytes(m.data)))
        if out:
            self.board._request({"cmd": "can", "frames": out, "source": "host"})
            self.n_to_board += len(out)
        return len(out)

    def from_board(self, r: StepResult) -> None:
        """Put the frames the board sent during ``r`` on the python-can bus."""
        for cyc, cid, data in r.can_tx:
            self.bus.send(self._can.Message(timestamp=cyc / (CYCLES_PER_US * 1e6), arbitration_id=cid, data=data,
                                            is_extended_id=False))
            self.n_from_board += 1
            if self._sent is not None:
                self._sent.append((int(cid), bytes(data)))
            if self.log:
                self.frames.append((cyc, "tx", cid, data))

    def inject(self, frames: list[tuple[int, bytes]], source: str = "other") -> None:
        """Frames from another node straight onto the emulated bus (bus load), FIFO per ``source``."""
        if frames:
            self.board._request({"cmd": "can", "frames": [[int(i), bytes(d).hex()] for i, d in frames],
                                 "source": source})

    def disturb(self, on: bool = True) -> dict[str, Any]:
        """Disturb the bus (every transmission attempt an error frame) or end it; the chip's state."""
        return dict(self.board._request({"cmd": "can_bus", "error": bool(on)})["can"])

    def run(self, us: float) -> StepResult:
        self.to_board()
        r = self._board_run(us)
        self.from_board(r)
        return r

    def close(self) -> None:
        self.board.run = self._board_run  # type: ignore[method-assign]
        if self._own:
            self.bus.shutdown()


class CanBoard:
    """An emulated Pico running ``main.py`` with the CAN link, bridged to a python-can bus.

    Behaves as its :class:`EmulatedBoard` (attributes are passed through) except that
    :meth:`run` moves frames both ways (:class:`CanBridge`).

    Parameters
    ----------
    bus, channel, interface
        The python-can side (see :class:`CanBridge`).
    bundle_dir, firmware
        As :class:`EmulatedBoard`.
    main : bool
        Run ``main.main(link="can")`` at boot (else the REPL, the controller attached).
    attach : bool
        ``False``: no controller on SPI (the wiring fault).
    start_us : float
        Board time allowed for the firmware to bring the controller to normal mode.
    adc : int, optional
        ADC0 input held from the start (the emulated HIL drives it itself).

    Raises
    ------
    BoardError
        The board did not boot, raised, or (``main``, ``attach``) did not start its controller.
    """

    def __init__(self, bus: Any = None, *, channel: str = "upright-emu", interface: str = "virtual",
                 bundle_dir: Path | None = None, firmware: Path = FIRMWARE, main: bool = True, attach: bool = True,
                 xtal_hz: int | None = None, start_us: float = 2_000_000, adc: int | None = None) -> None:
        files = {"main.py": CAN_MAIN} if main else {}
        b = EmulatedBoard(bundle_dir, firmware=firmware, main=False, files=files,
                          harness_args=harness_args(xtal_hz=xtal_hz, attach=attach))
        self.board = b
        try:
            if adc is not None:
                b.set_adc(int(adc))  # the pendulum held (upright at the pot offset for the tools)
            self.bridge = CanBridge(b, bus, channel=channel, interface=interface)
            if main:
                b.main = True  # a traceback on the console is a BoardError from now on
                if attach:
                    t = 0.0
                    while True:
                        r = self.bridge.run(10_000)
                        t += 10_000
                        if r.can.get("mode") == 0:
                            break
                        if t >= start_us:
                            raise b._fail(f"the firmware did not start its CAN controller within "
                                          f"{start_us / 1000:.0f} ms of board time (mode {r.can.get('mode')})")
        except BaseException:
            bridge = getattr(self, "bridge", None)
            if bridge is not None:
                bridge.close()
            b.close()
            raise

    def run(self, us: float) -> StepResult:
        return self.bridge.run(us)

    def serve(self, stop: Callable[[], bool] = lambda: False, *, chunk_us: float = 2000.0) -> None:
        """Run until ``stop()`` is true, ``chunk_us`` of board time at a time, never faster than
        real time, moving frames both ways (``upright emulate rp2040 --can``).

        Raises
        ------
        BoardError
            The board raised or stopped (quoting its last output).
        """
        t0 = time.monotonic()
        c0 = self.board.cycles
        fileno = getattr(self.bridge.bus, "fileno", lambda: -1)
        try:
            fd = int(fileno())
        except (NotImplementedError, OSError, ValueError):
            fd = -1
        while not stop():
            self.run(chunk_us)
            ahead = (self.board.cycles - c0) / (CYCLES_PER_US * 1e6) - (time.monotonic() - t0)
            if ahead > 0:
                # ahead of the wall clock: wait, but wake when a frame comes in
                select.select([fd] if fd >= 0 else [], [], [], ahead)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.board, name)

    def close(self) -> None:
        self.bridge.close()
        self.board.close()

    def __enter__(self) -> "CanBoard":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
