"""The gain tables the dashboard offers for upload: designs of the project, or a file.

* ``shipped`` -- the shipped design (``host.design.export.export()``: the table of
  ``firmware/gains.py``);
* ``place`` -- the report's pole placement, discretised and exported the same way;
* a file -- what ``upright export --out gains.py`` writes (its ``FLAT`` tuple, read with
  ``ast``: nothing in the file runs) or the raw upload bytes of ``upright export --blob``.

:func:`table_bytes` turns either into the upload bytes with a label; the board checks shape,
CRC and stability itself and refuses a bad table (the old one stays).
"""

from __future__ import annotations

import ast
import struct
from typing import Callable

from firmware import msgtable as T
from host.link import messages as M

__all__ = ["CHOICES", "design_table", "table_bytes", "TableError"]


class TableError(ValueError):
    """A file that is not a gain table (one line)."""


def _shipped() -> bytes:
    from host.design.export import export

    return export().blob()


def _place() -> bytes:
    from host.design.discrete import controller_ss
    from host.design.export import export
    from sim.params import load_params

    p = load_params()
    return export(p, controller_ss(p, design="place")).blob()


#: name -> (label, builder)
CHOICES: dict[str, tuple[str, Callable[[], bytes]]] = {
    "shipped": ("shipped design (firmware/gains.py: LQR, clamped)", _shipped),
    "place": ("the report's pole placement", _place),
}
_CACHE: dict[str, bytes] = {}


def design_table(name: str) -> tuple[bytes, str]:
    """Upload bytes and label of a named design (:data:`CHOICES`).

    Raises
    ------
    TableError
        Unknown name.
    """
    if name not in CHOICES:
        raise TableError(f"unknown table {name!r}; choose one of {', '.join(CHOICES)}")
    if name not in _CACHE:
        _CACHE[name] = CHOICES[name][1]()
    return _CACHE[name], CHOICES[name][0]


def table_bytes(data: bytes, filename: str = "file") -> tuple[bytes, str]:
    """Upload bytes and label of a table file: a gains module (``FLAT = (...)``) or raw bytes.

    Raises
    ------
    TableError
        Neither a gains module nor a whole number of int32 values within ``GAINS_MAX`` bytes.
    """
    flat = _flat_of_module(data)
    if flat is not None:
        try:
            blob = struct.pack(f"<{len(flat)}i", *flat)
        except struct.error as exc:
            raise TableError(f"{filename}: FLAT holds a value that is not an int32 ({exc})") from None
    else:
        blob = bytes(data)
    if not blob or len(blob) % 4 or len(blob) > T.GAINS_MAX:
        raise TableError(f"{filename}: not a gain table (a gains module with FLAT, or 4..{T.GAINS_MAX} bytes "
                         f"of int32 values; got {len(blob)} bytes)")
    return blob, f"{filename} (CRC {M.crc16(blob):#06x})"


def _flat_of_module(data: bytes) -> list[int] | None:
    try:
        tree = ast.parse(data.decode("utf-8"))
    except (UnicodeDecodeError, SyntaxError, ValueError):
        return None
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "FLAT" for t in node.targets):
            try:
                vals = ast.literal_eval(node.value)
            except ValueError:
                raise TableError("FLAT is not a literal tuple of integers") from None
            if not isinstance(vals, (tuple, list)) or not all(isinstance(v, int) and not isinstance(v, bool)
                                                             for v in vals):
                raise TableError("FLAT is not a tuple of integers")
            return list(vals)
    return None
