"""Every generated file of the project, and how to make it.

One table: output path -> ``"module:function"`` returning the file's full text from its
single source of truth.  ``make generate`` (``upright generate``) writes them;
``upright generate --check`` (and ``tests/test_generated.py``) fails when any is stale.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[2]

# path relative to the repository root -> renderer "module:function" (no arguments)
GENERATED: dict[str, str] = {
    "firmware/gains.py": "host.design.export:render_default",
    "firmware/fastpath.py": "host.boards.fwgen.fastpath:render_fastpath",
    "firmware/fasttick.py": "host.boards.fwgen.fasttick:render_fasttick",
    "firmware/fastframe.py": "host.boards.fwgen.fastframe:render_fastframe",
    "firmware/fastcan.py": "host.boards.fwgen.fastcan:render_fastcan",
    "firmware/fastlink.py": "host.boards.fwgen.fastlink:render_fastlink",
    "docs/upright.dbc": "host.link.dbc:render_default",
    "docs/protocol.md": "host.link.protodoc:render_protocol_md",
    "firmware/identity.py": "host.link.identity:render_identity",
}


def renderer(spec: str) -> Callable[[], str]:
    """Resolve a ``"module:function"`` renderer spec."""
    mod, func = spec.split(":")
    return getattr(importlib.import_module(mod), func)


def stale() -> list[str]:
    """Return the generated paths whose committed text differs from a fresh render."""
    out = []
    for rel, spec in GENERATED.items():
        path = ROOT / rel
        if not path.exists() or path.read_text() != renderer(spec)():
            out.append(rel)
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright generate``."""
    parser.add_argument("--check", action="store_true", help="only check; exit 1 if a generated file is stale")


def run(args: argparse.Namespace) -> int:
    """Write (or check) every generated file."""
    if args.check:
        bad = stale()
        for rel in bad:
            print(f"stale: {rel} (run `make generate`)", file=sys.stderr)
        return 1 if bad else 0
    for rel, spec in GENERATED.items():
        path = ROOT / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(renderer(spec)())
        print(f"wrote {rel}")
    return 0
