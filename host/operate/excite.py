"""Identification experiments on a board: the firmware's own excitation, recorded.

``upright board excite`` sends EXCITE (``firmware/excite.py``): the board plays a PRBS of
``+-amplitude`` N on its cart force, each bit held ``div`` control ticks, and stops it by
itself on disarm or a fault.  While it runs, the telemetry's x and phi are the sensors as
read and its force is the force applied, and the recording (every tick: ``telem_div`` is set
to 1 for the run and put back after) gets the column ``excite`` (the mode: 1 balancing,
2 cart-only) plus ``exc_amp_n`` and ``exc_div`` -- what ``upright identify`` reads.

- balancing run (default): arm, wait for balancing, PRBS added to the balancing force;
- cart-only run (``cart_only``; the pendulum removed or locked upright): the PRBS alone
  drives the cart open loop; after ``seconds`` the host disarms while the cart moves and
  records ``coast_s`` more seconds of the coast-down (driver off), which separates the
  cart's friction from the motor's back-EMF.

The board's limits apply: the amplitude at most half the gain table's force clamp (the
board refuses more), the sum clamped, the track and tilt faults.  The host-played
reference PRBS of earlier versions is gone: the firmware's is exact to the tick.

Durations are wall-clock seconds on the host (``seconds``, ``coast_s``) unless given in board
time (``board_seconds``, ``board_coast_s``): then they are counted in the board's own ticks --
one telemetry row per tick at ``telem_div`` 1, lost frames counted as ticks -- so a board
slower than real time (the emulated Pico, 0.05-0.4x here) still records that much of its
clock.  A fault latched while the excitation runs ends the run with :class:`BoardError` (the
rows stay on disk): a log that ends in a fault is not an identification experiment.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

from host.link import messages as M
from host.operate.board import Board, BoardError, fault_names, wait_state
from host.operate.record import Recorder

__all__ = ["EXTRA_COLUMNS", "MODES", "run_excite", "STALL_WALL_S", "STALL_BOARD_S"]

MODES = {"off": 0, "balancing": 1, "cart-only": 2}
EXTRA_COLUMNS = ("excite", "exc_amp_n", "exc_div")
STALL_WALL_S = 20.0
"""Wall seconds without a telemetry row after which a run in board time gives up ..."""
STALL_BOARD_S = 3.0
"""... or this many board seconds at the board's measured speed (:meth:`Board.wall`), if longer."""


def _excite_msg(mode: int, amplitude_n: float, div: int) -> Any:
    return M.BY_NAME["excite"](mode=mode, div=div, amp_mn=int(round(amplitude_n * 1000)))


def run_excite(b: Board, out: str | Path, *, seconds: float, amplitude_n: float, div: int = 4,
               cart_only: bool = False, coast_s: float = 3.0, arm: bool = True,
               board_seconds: float | None = None, board_coast_s: float | None = None,
               progress: Callable[[float, float, Recorder], None] | None = None) -> dict[str, Any]:
    """Run one identification experiment and record it to ``out`` (CSV or Parquet).

    Parameters
    ----------
    b : Board
        An open board.
    out : str or Path
        Recording (``.csv`` / ``.parquet``).
    seconds : float
        Excitation time (s of wall-clock time; ignored with ``board_seconds``).
    amplitude_n : float
        PRBS amplitude (N).
    div : int
        Control ticks per PRBS bit (1..255).
    cart_only : bool
        Open loop (mode 2) and a coast-down after it; else added to the balancing force.
    coast_s : float
        Cart-only: recording after the disarm (s of wall-clock time; ignored with ``board_coast_s``).
    arm : bool
        Arm first (clearing faults) and disarm at the end.
    board_seconds : float, optional
        Excitation time in board seconds (counted in the board's ticks, at its ``loop_rate_hz``).
    board_coast_s : float, optional
        Cart-only: the coast-down in board seconds.
    progress : callable, optional
        ``progress(elapsed, total, recorder)`` about 4 times a second (board seconds when the
        durations are in board time, else wall seconds).

    Returns
    -------
    dict
        The recorder's summary plus ``mode``, ``amplitude_n``, ``div`` and ``moved``: False
        when x and phi kept one value in every excited row (nothing moved: a dead drive,
        sensors that do not read -- ``upright identify`` refuses such a log), None without rows;
        ``board_s`` and ``coast_board_s``: the board time excited and coasting (its ticks / rate).

    Raises
    ------
    BoardError
        The board refused (e.g. not balancing, amplitude beyond half its force clamp),
        did not answer, faulted during the run (the flags named), sent no telemetry for
        :data:`STALL_WALL_S` in board time, or the link was lost; every row received is on disk.
    """
    mode = MODES["cart-only" if cart_only else "balancing"]
    board_time = board_seconds is not None or board_coast_s is not None
    try:
        rate = float(b.param_get("loop_rate_hz"))
    except BoardError as exc:
        if board_time:
            raise BoardError(f"{b.port}: cannot count board time, the board does not say its loop rate "
                             f"(loop_rate_hz): {exc}") from exc
        rate = 0.0
    ex_s = float(board_seconds) if board_seconds is not None else float(seconds)
    co_s = float(board_coast_s) if board_coast_s is not None else float(coast_s)
    old_div = b.param_get("telem_div")
    if old_div != 1:
        b.param_set("telem_div", 1)
    rec = Recorder(b, out, extra=EXTRA_COLUMNS)
    rec.extra_values.update(excite=0, exc_amp_n=0.0, exc_div=0)
    armed_here = False
    started = False
    moved: bool | None = None
    total = (ex_s if board_seconds is not None else seconds) + (co_s if cart_only else 0.0)
    fault: list[int] = []

    def watch(msg: Any, seq: int | None, t: float) -> None:
        # a heartbeat with a fault flag while the excitation runs (after the board's ACK)
        if started and msg.NAME == "heartbeat" and msg.faults and not fault:
            fault.append(int(msg.faults))

    ticks0 = 0
    ex_ticks = co_ticks = 0
    try:
        if arm:
            if b.state(fresh=True)["faults"]:
                b.clear_faults()
            b.arm()
            armed_here = True
        st = wait_state(b, ("balancing",), b.wall(5.0))
        if st != "balancing":
            raise BoardError(f"{b.port}: the board is {st}, not balancing: the excitation starts only while "
                             "balancing (pendulum upright, or locked upright for a cart-only run)")
        b.listeners.append(watch)
        b.request(_excite_msg(mode, amplitude_n, div))
        started = True
        # the column says the mode from the first row received after the board's ACK (rows
        # before it still carry the estimate, not the sensors)
        rec.extra_values.update(excite=mode, exc_amp_n=float(amplitude_n), exc_div=int(div))
        rec.reset_span()

        def ticks() -> int:
            # the board's ticks since the start: one row each, a lost pair of frames one more
            return rec.rows + rec.seqs.lost // 2 - ticks0

        ticks0 = ticks()
        stall_s = max(STALL_WALL_S, b.wall(STALL_BOARD_S))
        t0 = time.monotonic()
        last = -1.0
        disarmed = False
        coast_span = False
        seen, seen_t = 0, t0
        t_dis = 0.0
        n_dis = 0
        while True:
            now = time.monotonic()
            n = ticks()
            if n != seen:
                seen, seen_t = n, now
            elif board_time and now - seen_t > stall_s:
                raise BoardError(f"{b.port}: no telemetry for {stall_s:.0f} s of wall time "
                                 f"({n / rate:.2f} board s recorded)")
            if fault:
                raise BoardError(f"{b.port}: the board faulted during the excitation "
                                 f"({', '.join(fault_names(fault[0]))}): not an identification log")
            # elapsed time of each phase: board ticks / rate where asked, else the wall clock
            el_ex = n / rate if board_seconds is not None else now - t0
            if not disarmed:
                el = el_ex
                if el_ex >= ex_s:
                    ex_ticks = n
                    if not cart_only:
                        break
                    # the coast-down: driver off while the cart moves (the board's excitation
                    # stops, its telemetry keeps sending the sensors)
                    b.disarm()
                    disarmed = True
                    t_dis, n_dis = time.monotonic(), ticks()
            if disarmed:
                el_co = (ticks() - n_dis) / rate if board_coast_s is not None else time.monotonic() - t_dis
                el = ex_s + el_co
                if el_co >= co_s:
                    co_ticks = ticks() - n_dis
                    break
            if disarmed and not coast_span:
                coast_span = True
                moved = rec.moved()
            if not disarmed:
                b.keepalive()
            b.poll(0.02)
            if progress is not None and el - last >= 0.25:
                last = el
                progress(el, total, rec)
        if progress is not None:
            progress(total, total, rec)
        if not coast_span:
            moved = rec.moved()
        if fault:
            raise BoardError(f"{b.port}: the board faulted during the excitation "
                             f"({', '.join(fault_names(fault[0]))}): not an identification log")
    except BoardError as exc:
        failure: BoardError | None = exc
    else:
        failure = None
    finally:
        try:
            if started:
                b.request(_excite_msg(0, 0.0, 1))
        except Exception:  # noqa: BLE001 - the board may be gone; the rows still go to disk
            pass
        rec.extra_values.update(excite=0, exc_amp_n=0.0, exc_div=0)
        if watch in b.listeners:
            b.listeners.remove(watch)
        if armed_here:
            b.safe_disarm()
            b.armed_by_us = False
        try:
            if old_div != 1:
                b.param_set("telem_div", old_div)
        except Exception:  # noqa: BLE001 - as above
            pass
        rec.close()
    if failure is not None:
        raise BoardError(f"{failure} (kept {rec.rows} rows in {out})") from failure
    s = rec.summary()
    r_ = float(rate) if rate else float("nan")
    s.update(mode=mode, amplitude_n=amplitude_n, div=div, moved=moved, board_s=ex_ticks / r_ if rate else None,
             coast_board_s=co_ticks / r_ if rate and cart_only else None,
             span={k: tuple(v) for k, v in rec.span.items()})
    return s
