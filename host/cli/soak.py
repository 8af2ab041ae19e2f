"""``upright soak`` (``make soak``): one long lockstep HIL run that must leave no trace in the firmware.

What is checked is in :mod:`host.hil.soak`.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Sequence

from host.cli import args as A
from host.hil.errors import HilError
from host.hil.soak import PERIOD_S, SoakResult, soak

MAX_SOAK_S = 7 * 24 * 3600.0


# ---------------------------------------------------------------- command line
def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright soak`` / ``python -m host.cli.soak``."""
    parser.add_argument("--sim-seconds", type=A.duration(MAX_SOAK_S), default=3600.0, metavar="S",
                        help="simulated time (default 3600, at most a week)")
    parser.add_argument("--link", choices=("serial", "can"), default="serial", help="framing (default serial)")
    parser.add_argument("--chunk", type=A.positive, default=None, metavar="S",
                        help="seconds per metrics chunk, whole 4.4 s periods (default: a tenth of the run)")
    parser.add_argument("--tolerance", type=A.in_range(0.0, 1.0, lo_open=True, hi_open=True), default=0.1,
                        help="relative difference allowed between chunks' metrics (default 0.1)")
    parser.add_argument("--quiet", action="store_true", help="no progress output")


def run(args: argparse.Namespace) -> int:
    """Run the soak and print the summary; 0 if every check passed."""
    t0 = time.perf_counter()

    def prog(done: float, total: float) -> None:
        if not args.quiet:
            el = time.perf_counter() - t0
            print(f"  {done:8.1f} / {total:g} s simulated, {el:6.0f} s wall", file=sys.stderr, flush=True)

    from host.cli.main import interrupted

    if not args.sim_seconds >= 2 * PERIOD_S:
        raise A.UsageError(f"--sim-seconds (sim_seconds) must be at least {2 * PERIOD_S:g} "
                           f"(two reference periods), got {args.sim_seconds:g}")
    res = SoakResult()
    try:
        soak(args.sim_seconds, link=args.link, chunk_s=args.chunk, tolerance=args.tolerance, progress=prog,
             result=res)
    except KeyboardInterrupt:
        _partial(res, args.sim_seconds)
        raise
    except (HilError, OSError, ValueError) as exc:
        if interrupted():
            _partial(res, args.sim_seconds)
            raise KeyboardInterrupt from None
        print(f"upright soak: {exc}", file=sys.stderr)
        return 1
    wall = time.perf_counter() - t0
    s, p = res.stats, res.stats.get("probe", {})
    print(f"soak: {args.sim_seconds:g} s simulated ({s.get('ticks', 0)} ticks) over the {args.link} link "
          f"in {wall:.0f} s wall ({args.sim_seconds / wall:.1f}x real time)")
    print(res.table())
    print(f"heap: gc.mem_alloc() {p.get('alloc0')} -> {p.get('alloc1')} bytes, heap_lock held the whole run: "
          f"{bool(p.get('locked'))}")
    print(f"firmware: {p.get('steps')} steps, {p.get('frames')} frames, decoder ok {p.get('n_ok')}")
    print(f"clock: board uptime advanced {s.get('uptime_advance_ms')} ms for {s.get('ticks')} ticks "
          f"of {s.get('period_ms')} ms")
    seq = (f", sequence: {s.get('seq_lost')} lost, {s.get('duplicates')} duplicated" if "seq_lost" in s else
           " (CAN frames carry no sequence number: counted only)")
    print(f"telemetry: {s.get('telemetry')} pairs for {s.get('ticks')} ticks / telem_div {s.get('telem_div')}{seq}")
    if res.ok:
        print("soak: PASS")
        return 0
    print("soak: FAIL")
    for msg in res.failures:
        print(f"  - {msg}")
    return 1


def _partial(res: SoakResult, total: float) -> None:
    """After Ctrl-C: the chunks that finished, marked partial (no verdict)."""
    done = res.chunks[-1]["t1"] if res.chunks else 0.0
    print(f"soak: PARTIAL: interrupted after {done:g} of {total:g} s simulated "
          f"({len(res.chunks)} chunk(s) finished); no verdict")
    if res.chunks:
        print(res.table())


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m host.cli.soak``."""
    parser = argparse.ArgumentParser(prog="python -m host.cli.soak", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
