"""Every generated file is up to date with its single source of truth."""

from __future__ import annotations

from host.cli import generate


def test_no_generated_file_is_stale() -> None:
    stale = generate.stale()
    assert not stale, f"stale generated files (run `make generate`): {stale}"


def test_every_generated_file_names_its_source() -> None:
    for rel, spec in generate.GENERATED.items():
        text = generate.renderer(spec)()
        head = "\n".join(text.splitlines()[:5]).lower()
        assert "generated" in head and "do not edit" in head, rel
