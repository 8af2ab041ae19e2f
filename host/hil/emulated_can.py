"""HIL on the emulated RP2040 over CAN: :mod:`host.hil.emulated` with the board's CAN link.

The board runs ``main.main(link="can")``: the same ``main.py`` loop, its host link an MCP2515 on
SPI1 (``firmware/link_can.py``), modelled at the register level by the harness and bridged to a
python-can bus (:mod:`host.boards.rp2040.can`).  The host end is the project's own
:class:`host.link.clients.CanLink` on that bus (python-can ``virtual``, one process): every
command of the scenario (set-up, ``arm``, the ``set_reference`` keep-alive) travels as a CAN frame
through python-can, the emulated bus (its bit time, arbitration) and the controller's receive
buffers, and every heartbeat/telemetry frame back the same way.  CAN frames carry no sequence
number: replies are matched by message id (``seq`` is ``None`` throughout).

``stats`` gain, besides :meth:`host.hil.emulated.EmulatedHil.run`'s: ``can_frames_in`` /
``can_frames_out`` (board's view), ``can_bus_load`` (fraction of board time the bus carried
frames), ``can_bit_ns``, ``can_spi_bytes`` and ``can_spi_us_per_tick`` (SPI transfer time per
loop iteration), ``can_tec``/``can_rec``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

from host.boards.rp2040.board import CYCLES_PER_US, FIRMWARE, StepResult
from host.boards.rp2040.can import CanBoard
from host.hil.emulated import EmulatedHil, run_all
from host.hil.results import HilRun
from host.link import messages as M
from sim.params import RobotParams, load_params
from sim.scenario import Scenario

__all__ = ["EmulatedCanHil", "run_emulated_can"]


class _CanHostSide:
    # the host end of the bus: host.link.clients.CanLink on the bridge's python-can channel
    def __init__(self, board: CanBoard, channel: str, node_id: int) -> None:
        from host.link.clients import CanLink

        self.board = board
        self.link = CanLink(interface="virtual", channel=channel, node_id=node_id)
        self.last_seq: int | None = None
        self.sent = 0

    def send(self, msg: M.Message) -> None:
        self.link.send(msg)
        self.board.bridge.to_board()  # onto the emulated bus at the current board time
        self.sent += 1
        return None

    def feed(self, data: bytes) -> list[tuple[M.Message, None]]:
        out = []
        while True:
            m = self.link.recv(0)
            if m is None:
                return out
            out.append((m, None))

    def close(self) -> None:
        self.link.close()


class EmulatedCanHil(EmulatedHil):
    """:class:`~host.hil.emulated.EmulatedHil` with the board's host link on CAN.

    Parameters
    ----------
    channel : str
        python-can ``virtual`` channel the bridge and the host link share.
    node_id : int
        The board's CAN node id (``node_id`` parameter; default 1).
    **kw
        As :class:`EmulatedHil` (``board`` must be a :class:`CanBoard` if given).
    """

    def __init__(self, bundle_dir: Path | None = None, *, channel: str = "upright-hil", node_id: int = 1,
                 **kw: Any) -> None:
        super().__init__(bundle_dir, **kw)
        self.channel = channel
        self.node_id = node_id

    def open(self) -> "EmulatedCanHil":
        import time

        t0 = time.perf_counter()
        if self.board is None:
            self.board = CanBoard(channel=self.channel, bundle_dir=self.bundle_dir, firmware=self.firmware)  # type: ignore[assignment]
        super().open()
        self.boot_wall_s = time.perf_counter() - t0
        self.host = _CanHostSide(self.board, self.channel, self.node_id)  # type: ignore[assignment,arg-type]
        return self

    def close(self) -> None:
        if self.host is not None:
            self.host.close()  # type: ignore[attr-defined]
            self.host = None
        super().close()

    def run(self, scenario: Scenario, params: RobotParams | None = None, **kw: Any) -> HilRun:
        b = self._b()
        can0 = b.run(0).can
        c0 = b.cycles
        run = super().run(scenario, params, **kw)
        can1 = b.run(0).can
        board_us = (b.cycles - c0) / CYCLES_PER_US
        ticks = max(1, round(board_us / run.stats.get("period_us", 2000.0)))

        def d(key: str) -> float:
            return float(can1.get(key, 0) - can0.get(key, 0))

        run.link = "can"
        run.stats.update({
            "can_frames_in": b.bridge.n_to_board, "can_frames_out": b.bridge.n_from_board,
            "can_bus_load": d("bus_busy_ns") / 1000 / board_us if board_us else 0.0,
            "can_bit_ns": can1.get("bit_ns"), "can_spi_bytes": int(d("spi_bytes")),
            "can_spi_us_per_tick": d("spi_busy_ns") / 1000 / ticks,
            "can_tec": can1.get("tec"), "can_rec": can1.get("rec"),
        })
        return run


def run_emulated_can(scenarios: Sequence[Scenario], *, out: str | Path | None = None, params: RobotParams | None = None,
                     compare: bool = True, gif: bool = True, plot: bool = True,
                     progress: Callable[[str, int, int], None] | None = None,
                     on_result: Callable[[HilRun], None] | None = None, bundle_dir: Path | None = None,
                     firmware: Path = FIRMWARE, board: CanBoard | None = None, channel: str = "upright-hil",
                     node_id: int = 1, plant: RobotParams | None = None) -> list[HilRun]:
    """:func:`host.hil.emulated.run_emulated` over CAN (same outputs; ``plant`` as there)."""
    with EmulatedCanHil(bundle_dir, firmware=firmware, board=board, channel=channel, node_id=node_id) as hil:  # type: ignore[arg-type]
        return run_all(hil, scenarios, params or load_params(), out=out, compare=compare, gif=gif, plot=plot,
                       progress=progress, on_result=on_result, plant=plant)
