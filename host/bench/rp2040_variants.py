"""Calibration variants of the board image: the same pinned sources, linked as other builds link them.

The shipped board image (:mod:`host.boards.rp2040.build`) is MicroPython 1.25 on pico-sdk 2.1.1
with one source edit, :data:`~host.boards.rp2040.build.LD_PATCH` (``py/vm.c``, ``py/gc.c`` and
``py/parse.c`` back in SRAM).  The calibration against real Picos (:mod:`host.bench.rp2040_calibration`)
needs two more images, each built from the same Debian sources and the same checksummed cache
into a directory of its own (never over ``build/rp2040/firmware.bin``):

``release``
    MicroPython 1.25 **as released**: without the linker patch, so the VM, GC and parser run from
    flash through the XIP cache (pico-sdk 2.x names objects ``*.c.o``, the script's patterns
    ``*vm.c.obj``; upstream fixed them in 2026, MicroPython PR #19370).  Against the shipped image
    it gives the flash -> SRAM gains PR #19370 measured on a Pico W.
``v1.22``
    The code placement and float routines of the MicroPython v1.22.0-preview build whose
    real-Pico scores are the reference (PR #12846, measured 2023-11-09): the linker patch (pico-sdk
    1.5.1 named objects ``.c.obj``, so v1.22 kept the VM, GC and parser in SRAM) **and** pico-sdk's
    own float implementation (``pico_set_float_implementation(... pico)``: the bootrom's float
    routines and pico-sdk's math functions).  MicroPython moved to its own ``lib/libm`` and a
    ``pico_float_micropython`` component in PR #13133, merged 2023-12-05, after the reference run;
    1.25's libm is ~34 % slower on ``bm_float`` in emulated cycles.  The rest of the 1.22 -> 1.25
    difference (the interpreter's own code, the compiler, the binary's layout) cannot be rebuilt:
    no Debian package or pinned registry tarball holds MicroPython 1.22 (docs/firmware.md).

``python -m host.bench.rp2040_variants NAME [--out DIR]`` builds ``DIR/firmware.bin`` (about a
minute on 2 cores); a present image built from the same inputs is reused.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

from host.boards.rp2040 import build as B

__all__ = ["FLOAT_FILE", "FLOAT_PATCH", "VARIANTS", "Variant", "build_variant"]

FLOAT_FILE: str = "ports/rp2/CMakeLists.txt"
"""The rp2 port's CMake file, where the float implementation is chosen."""

FLOAT_PATCH: tuple[str, str] = ("pico_set_float_implementation(${MICROPY_TARGET} micropython)",
                                "pico_set_float_implementation(${MICROPY_TARGET} pico)")
"""pico-sdk's float implementation instead of MicroPython's (as before MicroPython PR #13133)."""


@dataclass(frozen=True)
class Variant:
    """One calibration image: which of the two source edits it carries.

    Attributes
    ----------
    name : str
        ``release`` or ``v1.22`` (module docstring).
    what : str
        One line for the bench's notes.
    ld_patch : bool
        Apply :data:`host.boards.rp2040.build.LD_PATCH` (VM, GC, parser in SRAM).
    pico_float : bool
        Apply :data:`FLOAT_PATCH` (pico-sdk's float implementation).
    """

    name: str
    what: str
    ld_patch: bool
    pico_float: bool

    @property
    def default_out(self) -> Path:
        """``build/rp2040-NAME`` (a sibling of ``build/rp2040``)."""
        return B.REPO_ROOT / "build" / f"rp2040-{self.name}"

    def record(self) -> dict[str, object]:
        """What the image depends on: the board image's inputs and this variant's edits."""
        rec = {**B.inputs_record(), "variant": self.what, "ld_patch": self.ld_patch,
               "float_patch": [FLOAT_FILE, *FLOAT_PATCH] if self.pico_float else None}
        rec.pop("expected_firmware_sha256")
        return rec


VARIANTS: dict[str, Variant] = {
    "release": Variant("release", "MicroPython 1.25 as released (VM, GC, parser in flash)", False, False),
    "v1.22": Variant("v1.22", "1.25 linked as the v1.22 reference build (VM, GC, parser in SRAM; "
                     "pico-sdk's bootrom float routines)", True, True),
}
"""The calibration images by name."""


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    if text.count(old) != 1:
        raise B.BuildError(f"{path}: {old!r} not found once; the variant's edit does not apply to this source")
    path.write_text(text.replace(old, new))


def build_variant(name: str, out: Path | None = None, jobs: int = 2) -> Path:
    """Build (or reuse) the calibration image ``name``.

    Parameters
    ----------
    name : str
        A key of :data:`VARIANTS`.
    out : Path, optional
        Output directory (default :attr:`Variant.default_out`): ``firmware.bin``,
        ``firmware.elf``, ``inputs.json``; ``work/`` holds the build tree.
    jobs : int
        Parallel make jobs.

    Returns
    -------
    Path
        The variant's ``firmware.bin``.

    Raises
    ------
    KeyError
        ``name`` is not a variant.
    host.boards.rp2040.build.BuildError
        A pinned source is missing from the cache or differs from its pin, a source edit does
        not apply, or the compile fails.
    """
    v = VARIANTS[name]
    out = (out or v.default_out).resolve()
    record = json.loads(json.dumps(v.record()))
    fw = out / "firmware.bin"
    rec = out / "inputs.json"
    if fw.is_file() and rec.is_file() and json.loads(rec.read_text()) == record:
        return fw
    cache = B.DEFAULT_OUT / "cache"
    bad = [(p.name, why) for pkg in B.PINNED for p in pkg.files if (why := B.verify(cache, p))]
    if bad:
        raise B.BuildError("the pinned sources are not all in build/rp2040/cache (run `make rp2040` first): "
                           + "; ".join(f"{n}: {w}" for n, w in bad))
    B.check_toolchain()
    work = out / "work"
    mpy = B.lay_out(cache, work)
    if v.ld_patch:
        B.patch_linker_script(mpy)
    if v.pico_float:
        _edit(mpy / FLOAT_FILE, *FLOAT_PATCH)
    built = B.compile_firmware(mpy, work, jobs)
    out.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(built / "firmware.elf", out / "firmware.elf")
    shutil.copyfile(built / "firmware.bin", fw)
    rec.write_text(json.dumps(record, indent=1) + "\n")
    return fw


def main(argv: list[str] | None = None) -> int:
    """Command line: build one variant."""
    ap = argparse.ArgumentParser(prog="python -m host.bench.rp2040_variants", description=__doc__.splitlines()[0])
    ap.add_argument("name", choices=sorted(VARIANTS), help="the variant")
    ap.add_argument("--out", type=Path, default=None, help="output directory (default build/rp2040-NAME)")
    ap.add_argument("-j", "--jobs", type=int, default=2)
    a = ap.parse_args(argv)
    try:
        print(build_variant(a.name, a.out, a.jobs))
    except B.BuildError as e:
        print(f"rp2040_variants: error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
