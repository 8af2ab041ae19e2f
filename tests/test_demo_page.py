"""The ``make demo`` page (``out/demo/index.html``): the summary table with the text table's marks,
and no ``nan`` where a run has no float comparison.

One ``upright demo`` run (the firmware under the MicroPython unix port on a pty) on two short
scenarios: a small tilt that passes everything and is compared with the float design, and a start
at 0.3 rad, whose |phi| < 0.3 check fails as its ``[expect]`` says (``FAIL*``, its note under the
table) and which has no float comparison (it starts beyond the catch-mode threshold: ``n/a`` and
the reason, never ``nan``).  The page is parsed with ``html.parser`` and checked cell by cell
against the text table the same run printed.
"""

from __future__ import annotations

import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

SMALL = """name = "page_small_tilt"
description = "released at rest with 0.05 rad of tilt (short)"
duration = 1.0
[initial]
phi = 0.05
[expect]
settle = "any"
"""
BIG = """name = "page_big_tilt"
description = "released at rest with 0.3 rad of tilt (short)"
duration = 1.0
[initial]
phi = 0.3
[expect]
phi_max = "fail"
settle = "any"
a_max = "any"
note = "a run that starts at 0.3 rad cannot stay below 0.3 rad"
"""


class _Page(HTMLParser):
    """The summary table's cells (text and title) and the page's paragraphs."""

    def __init__(self) -> None:
        super().__init__()
        self.rows: list[list[tuple[str, str, str]]] = []  # (text, title, class) per cell
        self.paragraphs: list[str] = []
        self._in_table = False
        self._cell: list[str] | None = None
        self._attrs: dict[str, str] = {}
        self._p: list[str] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = {k: v or "" for k, v in attrs}
        if tag == "table" and a.get("id") == "summary":
            self._in_table = True
        elif self._in_table and tag == "tr":
            self.rows.append([])
        elif self._in_table and tag in ("td", "th"):
            self._cell, self._attrs = [], a
        elif tag == "p":
            self._p = []

    def handle_endtag(self, tag: str) -> None:
        if tag == "table":
            self._in_table = False
        elif tag in ("td", "th") and self._cell is not None:
            self.rows[-1].append(("".join(self._cell).strip(), self._attrs.get("title", ""), self._attrs.get("class", "")))
            self._cell = None
        elif tag == "p" and self._p is not None:
            self.paragraphs.append("".join(self._p))
            self._p = None

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.append(data)
        if self._p is not None:
            self._p.append(data)


@pytest.mark.slow
def test_the_demo_page_has_the_summary_table_with_its_marks_and_no_nan(tmp_path: Path) -> None:
    (tmp_path / "small.toml").write_text(SMALL)
    (tmp_path / "big.toml").write_text(BIG)
    r = subprocess.run([sys.executable, "-m", "host.cli.main", "demo", "--scenario",
                        f"{tmp_path / 'small.toml'},{tmp_path / 'big.toml'}", "--no-gif", "--no-design", "--quiet",
                        "--out", str(tmp_path / "out")], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    text_rows = {ln.split()[0]: ln.split() for ln in r.stdout.splitlines() if ln.startswith("page_")}
    html = (tmp_path / "out" / "demo" / "index.html").read_text()
    assert "nan" not in html.lower().replace("nan-", "")
    page = _Page()
    page.feed(html)
    head = [c[0] for c in page.rows[0]]
    assert head[0] == "scenario" and head[-1].startswith("|phi_hil - phi_float|")
    checks = [h for h in head if h in ("|phi|<0.3", "Ts<2.5s", "|a|<=5")]
    assert len(checks) == 3
    rows = {row[0][0]: dict(zip(head, row)) for row in page.rows[1:]}
    assert set(rows) == {"page_small_tilt", "page_big_tilt"}

    # the marks are the text table's, check by check (PASS, FAIL* expected, ! unexpected)
    for name, row in rows.items():
        txt = text_rows[name]
        assert [row[c][0] for c in checks] == txt[-3:], (name, row, txt)
        assert row["|phi|max (rad)"][0] == txt[1]
    small, big = rows["page_small_tilt"], rows["page_big_tilt"]
    assert [small[c][0] for c in checks] == ["PASS", "PASS", "PASS"]
    assert big["|phi|<0.3"][0] == "FAIL*" and "expected: fail" in big["|phi|<0.3"][1]
    assert "unexpected" not in big["|phi|<0.3"][2]

    # the float comparison: a number for the small tilt, n/a with its reason for the big one
    cmp_ = head[-1]
    assert 0.0 <= float(small[cmp_][0]) < 0.01
    assert big[cmp_][0].startswith("n/a") and "catch-mode threshold (0.2 rad)" in big[cmp_][1]

    # under the table: the counts, the expected FAIL's note, the reason of the n/a
    paras = " ".join(page.paragraphs)
    assert "2 runs, 1 constraint FAIL(s) (1 expected and documented, marked *), 0 unexpected outcome(s)" in paras
    assert "page_big_tilt: a run that starts at 0.3 rad cannot stay below 0.3 rad" in paras
    assert "no comparison with the float design: page_big_tilt: starts at |phi| = 0.30 rad" in paras
    # and in the run's own section
    assert "|phi_hil - phi_float| = n/a (starts at |phi| = 0.30 rad" in paras
    assert "|phi|&lt;0.3: FAIL*" in html
