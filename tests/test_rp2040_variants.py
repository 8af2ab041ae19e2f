"""The calibration images (host/bench/rp2040_variants.py): each variant's source edits are the ones
its docstring names, they apply to the pinned 1.25 source exactly once, and a source they do not fit
is refused by name rather than built as something else."""

from __future__ import annotations

from pathlib import Path

import pytest

from host.bench import rp2040_variants as V
from host.boards.rp2040 import build as B

SOURCE = B.DEFAULT_OUT / "work" / B.MICROPYTHON_DIR


def test_the_variants_carry_the_edits_they_name() -> None:
    rel, ref = V.VARIANTS["release"], V.VARIANTS["v1.22"]
    assert (rel.ld_patch, rel.pico_float) == (False, False)
    assert (ref.ld_patch, ref.pico_float) == (True, True)
    r1, r2 = rel.record(), ref.record()
    assert r1 != r2 and r1["packages"] == r2["packages"] == B.inputs_record()["packages"]
    assert r2["float_patch"] == [V.FLOAT_FILE, *V.FLOAT_PATCH] and r1["float_patch"] is None
    assert rel.default_out.name == "rp2040-release" and ref.default_out.parent == rel.default_out.parent


def test_an_edit_that_does_not_fit_the_source_is_refused(tmp_path: Path) -> None:
    f = tmp_path / "CMakeLists.txt"
    f.write_text("pico_set_float_implementation(${MICROPY_TARGET} compiler)\n")
    with pytest.raises(B.BuildError, match="not found once"):
        V._edit(f, *V.FLOAT_PATCH)
    f.write_text(V.FLOAT_PATCH[0] + "\n" + V.FLOAT_PATCH[0] + "\n")  # twice: ambiguous
    with pytest.raises(B.BuildError, match="not found once"):
        V._edit(f, *V.FLOAT_PATCH)
    f.write_text("x\n" + V.FLOAT_PATCH[0] + "\ny\n")
    V._edit(f, *V.FLOAT_PATCH)
    assert f.read_text() == "x\n" + V.FLOAT_PATCH[1] + "\ny\n"


def test_the_float_edit_fits_the_pinned_source_once() -> None:
    cm = SOURCE / V.FLOAT_FILE
    if not cm.is_file():
        pytest.skip(f"{cm} missing: `make rp2040` unpacks the pinned source")
    assert cm.read_text().count(V.FLOAT_PATCH[0]) == 1
    assert (SOURCE / B.LD_FILE).is_file()
