"""tests/README.md is the index from behaviour to test: it names every test file, and every test
it names by ``file::function`` exists."""

from __future__ import annotations

import ast
import re
from pathlib import Path

HERE = Path(__file__).resolve().parent


def test_the_index_names_every_test_file_and_only_tests_that_exist() -> None:
    text = (HERE / "README.md").read_text()
    named = set(re.findall(r"`(test_\w+\.py)", text))
    files = {p.name for p in HERE.glob("test_*.py")}
    globbed = {f for f in files if any(re.fullmatch(g.replace("*", r"\w*"), f)
                                       for g in re.findall(r"`(test_\w*\*\.py)`", text))}
    assert files - named - globbed == set(), "tests/README.md does not index these test files"
    assert named - files == set(), "tests/README.md names test files that do not exist"
    for fname, func in re.findall(r"`(test_\w+\.py)::(\w+)`", text):
        tree = ast.parse((HERE / fname).read_text())
        defs = {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
        assert func in defs, f"tests/README.md names {fname}::{func}, which does not exist"
