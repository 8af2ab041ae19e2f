"""A calibration variant of the board image: MicroPython 1.25 with its VM, GC and parser in SRAM.

The rp2 port's linker script (``ports/rp2/memmap_mp_rp2040.ld``) means to keep ``py/vm.c``,
``py/gc.c`` and ``py/parse.c`` out of flash with the patterns ``*vm.c.obj`` etc., but pico-sdk
2.x names objects ``*.c.o``, so in the 1.25 image they run from flash through the XIP cache.
MicroPython 1.22 (pico-sdk 1.5.1, the release the published real-Pico scores of
``rp2040_perfbench_published.toml`` come from) kept them in SRAM; upstream restored that in 2026
(MicroPython PR #19370).  This module builds the same Debian 1.25 sources as
:mod:`host.boards.rp2040.build` (the pinned, checksummed cache) with only those three patterns
corrected to ``.c.o``, into a directory of its own (never over ``build/rp2040/firmware.bin``).

``python -m host.bench.rp2040_ramvm --out DIR`` builds ``DIR/firmware.bin`` (about a minute on
2 cores); a present image built from the same inputs is reused.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from host.boards.rp2040 import build as B

__all__ = ["DEFAULT_OUT", "LD_FILE", "PATCH", "build_ram_vm"]

DEFAULT_OUT: Path = B.REPO_ROOT / "build" / "rp2040-ramvm"
"""Where the variant goes by default (a sibling of ``build/rp2040``)."""

LD_FILE: str = B.LD_FILE
"""The linker script the patch changes (relative to the MicroPython tree)."""

PATCH: tuple[tuple[str, str], ...] = B.LD_PATCH
"""The one textual change: the object-name patterns as pico-sdk 2.x names the objects (the board
image, :mod:`host.boards.rp2040.build`, carries the same patch since issue 26 item 3)."""


def build_ram_vm(out: Path = DEFAULT_OUT, jobs: int = 2) -> Path:
    """Build (or reuse) the variant image.

    Parameters
    ----------
    out : Path
        Output directory: ``firmware.bin``, ``firmware.elf``, ``inputs.json``; ``work/`` holds
        the build tree.
    jobs : int
        Parallel make jobs.

    Returns
    -------
    Path
        The variant's ``firmware.bin``.

    Raises
    ------
    host.boards.rp2040.build.BuildError
        A pinned source is missing from the cache or differs from its pin, the linker script
        does not hold the pattern, or the compile fails.
    """
    out = out.resolve()
    record = {**B.inputs_record(), "variant": "vm.c, gc.c, parse.c in SRAM", "patch": [LD_FILE, *PATCH]}
    fw = out / "firmware.bin"
    rec = out / "inputs.json"
    if fw.is_file() and rec.is_file() and json.loads(rec.read_text()) == json.loads(json.dumps(record)):
        return fw
    cache = B.DEFAULT_OUT / "cache"
    bad = [(p.name, why) for pkg in B.PINNED for p in pkg.files if (why := B.verify(cache, p))]
    if bad:
        raise B.BuildError("the pinned sources are not all in build/rp2040/cache (run `make rp2040` first): "
                           + "; ".join(f"{n}: {w}" for n, w in bad))
    B.check_toolchain()
    work = out / "work"
    mpy = B.lay_out(cache, work)
    B.patch_linker_script(mpy)
    built = B.compile_firmware(mpy, work, jobs)
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(built / "firmware.elf", out / "firmware.elf")
    shutil.copyfile(built / "firmware.bin", fw)
    rec.write_text(json.dumps(record, indent=1) + "\n")
    return fw


def main(argv: list[str] | None = None) -> int:
    """Command line: build the variant."""
    ap = argparse.ArgumentParser(prog="python -m host.bench.rp2040_ramvm", description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output directory (%(default)s)")
    ap.add_argument("-j", "--jobs", type=int, default=2)
    a = ap.parse_args(argv)
    try:
        print(build_ram_vm(a.out, a.jobs))
    except B.BuildError as e:
        print(f"rp2040_ramvm: error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
