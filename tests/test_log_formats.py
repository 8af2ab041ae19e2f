"""docs/logs.md documents every column the recorders write, with the code's unit (issue 22)."""

from __future__ import annotations

import re
from pathlib import Path

import pyarrow.parquet as pq

from host.link import messages as M
from host.operate.excite import EXTRA_COLUMNS
from host.operate.record import COLUMNS, UNITS, Recorder
from sim.plantsim import LOG_COLUMNS

DOC = Path(__file__).resolve().parent.parent / "docs" / "logs.md"


def _section(title: str) -> dict[str, str]:
    # column -> unit cell of the first table under the heading that starts with title
    text = DOC.read_text().split("## " + title, 1)[1].split("\n## ", 1)[0]
    rows: dict[str, str] = {}
    for ln in text.splitlines():
        cells = [c.strip() for c in ln.strip().strip("|").split("|")]
        if len(cells) >= 3 and cells[0].startswith("`"):
            names = re.findall(r"`([a-z_]+)`", cells[0])
            units = [u.strip() for u in cells[1].split(",")]
            for i, n in enumerate(names):
                rows[n] = units[i] if i < len(units) else units[-1]
    return rows


def _unit(u: str) -> str:
    return {"–": "", "µs": "us", "m/s²": "m/s^2"}.get(u, u)


def test_board_recording_columns_and_units_are_documented() -> None:
    doc = _section("Board recordings")
    for c in (*COLUMNS, *EXTRA_COLUMNS):
        assert c in doc, f"docs/logs.md: board recording column {c!r} is not documented"
        assert _unit(doc[c]) == UNITS[c], (c, doc[c], UNITS[c])
    assert set(doc) == set(COLUMNS) | set(EXTRA_COLUMNS), set(doc) ^ (set(COLUMNS) | set(EXTRA_COLUMNS))


def test_simulation_log_columns_and_units_are_documented() -> None:
    doc = _section("Simulation and HIL runs")
    for c, text in LOG_COLUMNS.items():
        if c not in doc:
            continue  # the HIL extras are referred to LOG_COLUMNS by the page
        unit = text.split(",", 1)[0].strip()
        if unit.startswith("PWM") or unit == "count":
            unit = "count"
        assert _unit(doc[c]) == unit, (c, doc[c], unit)
    for c in ("t", "x", "xdot", "phi", "phidot", "x_ref", "adc", "enc", "duty", "force", "f_dist", "xddot", "u_cmd"):
        assert c in doc and c in LOG_COLUMNS, c


class _Listeners:
    # the Recorder only appends itself to the board's listeners: the frames come from the test
    def __init__(self) -> None:
        self.listeners: list = []


def test_parquet_recording_carries_the_units(tmp_path: Path) -> None:
    board = _Listeners()
    path = tmp_path / "run.parquet"
    rec = Recorder(board, path, extra=EXTRA_COLUMNS)
    on = board.listeners[0]
    on(M.BY_NAME["heartbeat"](state=2, faults=0, boot=1, epoch=0, gains_crc=0, uptime_ms=0), 0, 0.0)
    on(M.BY_NAME["telem_state"](x=1000, xdot=0, phi=100, phidot=0), 1, 0.001)
    on(M.BY_NAME["telem_ctrl"](ref=0, force=0, duty=0, step_us=400), 1, 0.001)
    rec.close()
    table = pq.read_table(path)
    assert table.num_rows == 1
    assert table.schema.metadata[b"upright.log"].startswith(b"board recording")
    for c in (*COLUMNS, *EXTRA_COLUMNS):
        assert table.schema.field(c).metadata[b"unit"].decode() == UNITS[c], c
