"""Record a board's telemetry: every frame a row, every lost frame counted, every row kept.

A :class:`Recorder` listens to a :class:`host.operate.board.Board` and turns each pair
TELEM_STATE + TELEM_CTRL (one control tick) into a row, with the host time, the board's
sequence number, the latest heartbeat's state and faults and any extra columns the caller
sets (``excite`` adds the excitation's mode, amplitude and bit length).  The board's pacer numbers its periodic
frames (heartbeats and telemetry) with one counter, so a gap in it is a lost frame
(:class:`host.hil.accounting.SeqAccount`, the one loss counter; serial framing; CAN frames carry no sequence number and losses are not counted there).

Rows go to disk as they come: CSV flushed at least every ``flush_s`` s, Parquet (``.parquet``
or ``.pq``, pyarrow) in row groups of the same interval -- so Ctrl-C, a closed link or an
exception loses nothing already received (:meth:`Recorder.close` runs in ``finally``).
"""

from __future__ import annotations

import csv
import time
from pathlib import Path
from typing import Any

from host.hil.accounting import SeqAccount, TickPairs

__all__ = ["TELEMETRY", "COLUMNS", "UNITS", "Recorder", "format_of", "telemetry_values"]

TELEMETRY = ("x", "xdot", "phi", "phidot", "ref", "force", "duty", "step_us", "state", "faults")
"""The columns of one control tick, the same in every recording (this recorder's, the dashboard's
:data:`host.dashboard.hub.COLUMNS`): the two telemetry frames in physical units and the state and
fault flags of the latest heartbeat (:func:`telemetry_values`)."""

COLUMNS = ("t", "seq", *TELEMETRY)
UNITS: dict[str, str] = {
    "t": "s", "seq": "", "x": "m", "xdot": "m/s", "phi": "rad", "phidot": "rad/s", "ref": "m", "force": "N",
    "duty": "count", "step_us": "us", "state": "", "faults": "",
    # the columns ``upright board excite`` adds (host/operate/excite.py)
    "excite": "", "exc_amp_n": "N", "exc_div": "tick",
}
"""Unit of each recorded column ('' for codes and counters; docs/logs.md says what each means).
Parquet files carry it as the field metadata ``unit``."""


def telemetry_values(st: Any, ct: Any, state: int, faults: int) -> tuple[Any, ...]:
    """The :data:`TELEMETRY` values of a tick's TELEM_STATE ``st`` and TELEM_CTRL ``ct``."""
    a, b = st.physical(), ct.physical()
    return (a["x"], a["xdot"], a["phi"], a["phidot"], b["ref"], b["force"], b["duty"], b["step_us"], state, faults)


def format_of(path: str | Path) -> str:
    """``"csv"`` or ``"parquet"`` from a file name (anything else: ValueError)."""
    suf = Path(path).suffix.lower()
    if suf in (".csv", ".txt"):
        return "csv"
    if suf in (".parquet", ".pq"):
        return "parquet"
    raise ValueError(f"{str(path)!r}: record to .csv or .parquet")


class Recorder:
    """Telemetry rows from a board into a file.

    Parameters
    ----------
    board : Board
        Its messages are observed (:attr:`Board.listeners`).
    path : str or Path
        ``.csv`` or ``.parquet``.
    extra : sequence of str
        Extra columns; their values are :attr:`extra_values` at the time of each row.
    flush_s : float
        Longest time between writes to disk.
    """

    def __init__(self, board: Any, path: str | Path, extra: tuple[str, ...] = (), flush_s: float = 0.5) -> None:
        self.board = board
        self.path = Path(path)
        self.fmt = format_of(self.path)
        self.columns = (*COLUMNS, *extra)
        self.extra_values: dict[str, Any] = {k: None for k in extra}
        self.flush_s = float(flush_s)
        self.rows = 0
        self.telemetry_frames = 0  # TELEM_STATE and TELEM_CTRL received
        self.pairs = TickPairs()  # the one pairing and loss count (the dashboard's too)
        self.t0: float | None = None
        self._buf: list[tuple[Any, ...]] = []
        self._last_flush = time.monotonic()
        # the latest heartbeat the board tool has seen: the rows still queued in its link came after it
        # (Board observes the board's stream in order, replies included), -1 in a row: none yet
        hb = getattr(board, "heartbeat", None)
        self._state = None if hb is None else int(hb.state)
        self._faults = None if hb is None else int(hb.faults)
        self._closed = False
        #: smallest and largest x (m) and phi (rad) of the rows since :meth:`reset_span`
        self.span: dict[str, list[float]] = {}
        self.reset_span()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.fmt == "csv":
            self._fh = open(self.path, "w", newline="")
            self._csv = csv.writer(self._fh)
            self._csv.writerow(self.columns)
            self._fh.flush()
            self._pq = None
        else:
            import pyarrow as pa
            import pyarrow.parquet as pq

            self._pa = pa
            types = {"seq": pa.int32(), "duty": pa.int32(), "step_us": pa.int32(), "state": pa.int32(),
                     "faults": pa.int32()}
            fields = [pa.field(c, types.get(c, pa.float64()), metadata={"unit": UNITS.get(c, "")})
                      for c in self.columns]
            self._schema = pa.schema(fields, metadata={"upright.log": "board recording (docs/logs.md)"})
            self._pq = pq.ParquetWriter(str(self.path), self._schema)
            self._fh = None
        board.listeners.append(self._on)

    # ---- accounting ----
    def reset_span(self) -> None:
        """Start :attr:`span` afresh (``excite``: from the first excited row)."""
        self.span = {"x": [float("inf"), float("-inf")], "phi": [float("inf"), float("-inf")]}

    def moved(self) -> bool | None:
        """Whether x or phi took more than one value in the rows since :meth:`reset_span`
        (``None``: no row)."""
        x, phi = self.span["x"], self.span["phi"]
        if x[0] > x[1]:
            return None
        return x[1] > x[0] or phi[1] > phi[0]

    @property
    def seqs(self) -> SeqAccount:
        """The sequence account of the periodic frames."""
        return self.pairs.seqs

    @property
    def unpaired(self) -> int:
        """Halves of a tick whose other half did not come."""
        return self.pairs.unpaired

    @property
    def lost(self) -> int:
        """Periodic frames lost (sequence gaps) plus halves of ticks whose pair was broken."""
        return self.pairs.lost

    def _on(self, msg: Any, seq: int | None, t: float) -> None:
        if self._closed:
            return
        name = msg.NAME
        if self.t0 is None:
            self.t0 = t
        if name == "heartbeat":
            self._state, self._faults = msg.state, msg.faults
        elif name in ("telem_state", "telem_ctrl"):
            self.telemetry_frames += 1
        pair = self.pairs.add(msg, seq, t) if name in ("heartbeat", "telem_state", "telem_ctrl") else None
        if pair is not None:
            st, ct, ts = pair
            a = st.physical()
            row = (round(ts - self.t0, 6), -1 if seq is None else seq,
                   *telemetry_values(st, ct, -1 if self._state is None else self._state,
                                     -1 if self._faults is None else self._faults),
                   *(self.extra_values[k] for k in self.columns[len(COLUMNS):]))
            self._buf.append(row)
            self.rows += 1
            for k, v in (("x", a["x"]), ("phi", a["phi"])):
                sp = self.span[k]
                if v < sp[0]:
                    sp[0] = v
                if v > sp[1]:
                    sp[1] = v
            if t - self._last_flush >= self.flush_s:
                self.flush()

    # ---- disk ----
    def flush(self) -> None:
        """Write the buffered rows to disk now."""
        self._last_flush = time.monotonic()
        if not self._buf:
            return
        rows, self._buf = self._buf, []
        if self._pq is None:
            self._csv.writerows(rows)
            self._fh.flush()
        else:
            cols = list(zip(*rows))
            arrays = [self._pa.array(list(c), type=self._schema.field(i).type) for i, c in enumerate(cols)]
            self._pq.write_table(self._pa.Table.from_arrays(arrays, schema=self._schema))

    def close(self) -> None:
        """Write what is left and close the file (idempotent; safe in ``finally``)."""
        if self._closed:
            return
        self._closed = True
        try:
            # a tick cut in half by the end of the recording is not a loss
            self.pairs.drop()
            self.flush()
        finally:
            if self._pq is not None:
                self._pq.close()
            if self._fh is not None:
                self._fh.close()
            try:
                self.board.listeners.remove(self._on)
            except ValueError:
                pass

    def summary(self) -> dict[str, Any]:
        """Rows written, telemetry frames received, frames lost."""
        return {"file": str(self.path), "rows": self.rows, "telemetry_frames": self.telemetry_frames,
                "lost": self.lost, "lost_periodic": self.seqs.lost, "unpaired": self.unpaired}
