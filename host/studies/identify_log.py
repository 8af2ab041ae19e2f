"""Reading the logs of ``upright board excite`` for ``upright identify`` (:mod:`host.studies.identify`).

A log is CSV or Parquet with the recorder's columns (:mod:`host.operate.record`); the rows
used are the first contiguous run with the excitation on (column ``excite``: 1 balancing,
2 cart-only), or all rows of a log without that column.  Every problem is a
:class:`LogError` naming the file and the column (and the line where there is one).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["LogError", "RunLog", "read_log", "REQUIRED"]

REQUIRED = ("x", "phi", "duty")
LEAD_ROWS = 25
"""Rows dropped at the start of a balancing run's excitation (50 ms at 500 Hz: the rows that
may still carry the estimate)."""


class LogError(ValueError):
    """A log cannot be used: names the file and, where it applies, the column."""

    def __init__(self, path: str, column: str, message: str) -> None:
        self.path, self.column = path, column
        where = f"{path}: column {column!r}: " if column else f"{path}: "
        super().__init__(where + message)


@dataclass
class RunLog:
    """One experiment: the rows it uses, as arrays (SI units, duty in counts).

    ``coast`` marks the coast-down rows of a cart-only run (driver off after the excitation).
    """

    name: str
    x: np.ndarray
    phi: np.ndarray
    duty: np.ndarray
    cart_only: bool
    coast: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    dt_mean: float = math.nan  # mean host-time spacing of the rows (s; NaN without a t column)


def _table(path: Path) -> dict[str, np.ndarray]:
    name = str(path)
    suf = path.suffix.lower()
    try:
        if suf in (".parquet", ".pq"):
            import pyarrow.parquet as pq

            t = pq.read_table(str(path))
            return {c: np.asarray(t.column(c).to_numpy(zero_copy_only=False)) for c in t.column_names}
        import csv

        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise LogError(name, "", f"cannot read: {exc.strerror or exc}") from exc
    except Exception as exc:  # noqa: BLE001 - a corrupt Parquet file, one line
        raise LogError(name, "", f"not a readable log: {exc}") from exc
    if not rows:
        raise LogError(name, "", "empty file (no header)")
    head = [h.strip() for h in rows[0]]
    out: dict[str, np.ndarray] = {}
    for j, col in enumerate(head):
        vals = []
        for i, r in enumerate(rows[1:], start=2):
            cell = r[j].strip() if j < len(r) else ""
            try:
                vals.append(float(cell) if cell not in ("", "None") else math.nan)
            except ValueError:
                if col in REQUIRED or col == "excite":
                    raise LogError(name, col, f"line {i}: not a number: {cell!r}") from None
                vals.append(math.nan)
        out[col] = np.asarray(vals, dtype=float)
    return out


def read_log(path: str | Path, cart_only: bool | None = None, min_rows: int = 500) -> RunLog:
    """Read a log of ``upright board excite`` (CSV or Parquet) into a :class:`RunLog`.

    Parameters
    ----------
    path : str or Path
        The file.
    cart_only : bool, optional
        Force the kind of run; default: from the ``excite`` column (2 = cart-only).
    min_rows : int
        Fewest excitation rows accepted.

    Raises
    ------
    LogError
        Unreadable file, missing or non-numeric column, too few rows, no excitation.
    """
    p = Path(path)
    name = str(p)
    cols = _table(p)
    for c in REQUIRED:
        if c not in cols:
            raise LogError(name, c, f"missing (a log of `upright board excite` has {', '.join(REQUIRED)}, excite)")
    exc = cols.get("excite")
    if exc is not None:
        modes = set(np.unique(exc[np.isfinite(exc)]).astype(int).tolist()) - {0}
        if not modes:
            raise LogError(name, "excite", "no row with an excitation (all 0): record with `upright board excite`")
        if len(modes) > 1:
            raise LogError(name, "excite", f"more than one excitation mode in one log: {sorted(modes)}")
        mode = modes.pop()
        if mode not in (1, 2):
            raise LogError(name, "excite", f"unknown excitation mode {mode} (1 balancing, 2 cart-only)")
        keep = exc == mode
        if cart_only is None:
            cart_only = mode == 2
    else:
        keep = np.ones(len(cols["x"]), dtype=bool)
        if cart_only is None:
            cart_only = False
    idx = np.flatnonzero(keep)
    if len(idx) and np.any(np.diff(idx) != 1):
        idx = idx[: int(np.flatnonzero(np.diff(idx) != 1)[0]) + 1]  # the first contiguous run
    if exc is not None and len(idx):
        # the first rows after the board's ACK may still carry the estimate, not the sensors
        # (a jump of x to the encoder's reading): a cart-only run starts at its first PRBS duty
        # (the cart at rest, as the fit assumes), a balancing run LEAD_ROWS in
        du = np.abs(cols["duty"][idx])
        if cart_only and np.all(np.isfinite(du)) and du.max() > 0:
            idx = idx[int(np.argmax(du >= 0.5 * du.max())):]
        else:
            idx = idx[min(LEAD_ROWS, len(idx)):]
    for c in REQUIRED:
        v = cols[c][idx]
        if not np.all(np.isfinite(v)):
            bad = int(idx[np.flatnonzero(~np.isfinite(v))[0]]) + 2
            raise LogError(name, c, f"line {bad}: missing or non-finite value")
    if len(idx) < min_rows:
        raise LogError(name, "", f"{len(idx)} excitation rows, at least {min_rows} needed")
    xs, ps = cols["x"][idx], cols["phi"][idx]
    if np.all(xs == xs[0]) and np.all(ps == ps[0]):
        # a frozen robot (dead drive, unwired sensors, an emulated board with nothing on its
        # pins): no fit can come of it, and LAPACK would only say so in its own words
        raise LogError(name, "", f"nothing moved: x ({xs[0]:g} m) and phi ({ps[0]:g} rad) are the same in every "
                                 f"one of the {len(idx)} excitation rows -- record again with the motor powered "
                                 "and the sensors wired (upright board excite warns when this happens)")
    seq = cols.get("seq")
    if seq is not None and np.all(np.isfinite(seq[idx])) and np.all(seq[idx] >= 0):
        # one sequence number per tick's telemetry pair, one more per heartbeat in between:
        # any other step is a lost tick, and the fit needs every tick
        gap = (np.diff(seq[idx].astype(np.int64)) % 256)
        bad = np.flatnonzero((gap != 1) & (gap != 2))
        if len(bad):
            raise LogError(name, "seq", f"line {int(idx[bad[0]]) + 3}: telemetry frames lost (sequence "
                                        f"jumps by {int(gap[bad[0]])}): record again (upright board excite "
                                        "counts the losses)")
    x, phi, duty = cols["x"][idx], cols["phi"][idx], cols["duty"][idx]
    coast = np.zeros(len(idx), dtype=bool)
    if cart_only:
        # the coast-down: the rows after the last powered one (driver off, duty 0)
        on = np.flatnonzero(duty != 0)
        if len(on) == 0:
            raise LogError(name, "duty", "cart-only run with the motor never driven")
        coast[on[-1] + 1:] = True
    else:
        if np.max(np.abs(phi)) > 0.5:
            raise LogError(name, "phi", f"|phi| reaches {np.max(np.abs(phi)):.2f} rad: the pendulum fell during "
                                        "the balancing run (use a smaller amplitude)")
    # host time says whether every tick was recorded -- unless upright board excite wrote the log
    # (it records at telem_div 1, and an emulated board's ticks are slower than the host's clock)
    t = cols.get("t") if "exc_div" not in cols else None
    dtm = math.nan
    if t is not None and np.all(np.isfinite(t[idx])):
        dtm = float(t[idx][-1] - t[idx][0]) / max(1, len(idx) - 1)
    return RunLog(name=name, x=x.astype(float), phi=phi.astype(float), duty=duty.astype(float),
                  cart_only=bool(cart_only), coast=coast, dt_mean=dtm)
