"""``make bench``: every speed figure of the project, measured side by side in one run.

Each benchmark is a ``"module:function"`` in :data:`BENCHES`; the function takes no
arguments and returns ``{"title": str, "rows": [dict, ...], "notes": [str, ...]}``.
Rows are printed as a table and everything is written to one JSON file.
Ratios between variants are the claim; absolute times depend on this noisy machine.
"""

from __future__ import annotations

import argparse
import importlib
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any, Sequence

# name -> "module:function"
BENCHES: dict[str, str] = {
    "batch": "host.bench.batch:bench",
    "robust": "host.bench.robust:bench",
    "proto": "host.bench.proto:bench_throughput",
    "proto_fuzz": "host.bench.proto:bench_fuzz",
    "firmware": "host.bench.firmware:bench",
    "hil": "host.bench.hil:bench_hil",
    "rp2040": "host.bench.rp2040:bench",
    "rp2040_calibration": "host.bench.rp2040_calibration:bench",
    "link": "host.bench.link_sweep:bench",
    "fuzz_states": "host.bench.fuzz_states:bench",
    "catch": "host.bench.catch:bench",
    "identify": "host.bench.identify:bench",
    "identify_dry": "host.bench.identify:bench_dry",
    "commission": "host.bench.commission:bench",
    "commission_rp2040": "host.bench.commission:bench_rp2040",
    "realism": "host.bench.realism:bench",
}


def _table(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return "  (no rows)"
    cols = list(dict.fromkeys(k for r in rows for k in r))
    cells = [[f"{r.get(c, ''):.4g}" if isinstance(r.get(c), float) else str(r.get(c, "")) for c in cols] for r in rows]
    widths = [max(len(c), *(len(row[i]) for row in cells)) for i, c in enumerate(cols)]
    line = "  " + "  ".join(c.ljust(w) for c, w in zip(cols, widths))
    body = ["  " + "  ".join(v.ljust(w) for v, w in zip(row, widths)) for row in cells]
    return "\n".join([line, "  " + "  ".join("-" * w for w in widths), *body])


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmarks (all, or those named with ``--only``) and write JSON."""
    ap = argparse.ArgumentParser(prog="python -m host.bench.main", description=__doc__)
    ap.add_argument("--out", default="out/bench.json", help="JSON file for the raw figures")
    ap.add_argument("--only", nargs="*", default=None, help="names of benchmarks to run")
    args = ap.parse_args(argv)
    names = args.only or list(BENCHES)
    results: dict[str, Any] = {"machine": platform.platform(), "python": sys.version.split()[0], "benches": {}}
    for name in names:
        mod, func = BENCHES[name].split(":")
        t0 = time.perf_counter()
        res = getattr(importlib.import_module(mod), func)()
        res["wall_s"] = time.perf_counter() - t0
        results["benches"][name] = res
        print(f"\n== {res.get('title', name)} ({res['wall_s']:.1f} s)")
        print(_table(res.get("rows", [])))
        for note in res.get("notes", []):
            print(f"  * {note}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2, default=float))
    print(f"\nraw figures: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
