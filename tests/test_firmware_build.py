"""Every firmware module compiles for the RP2040 and follows the firmware rules; the bundle builds."""

from __future__ import annotations

import ast
import importlib
import subprocess
from pathlib import Path

import pytest

from host.boards import bundle

FW = Path(__file__).resolve().parent.parent / "firmware"
MODULES = sorted(p.name for p in FW.glob("*.py"))
HARDWARE = {"hal_pico.py"}  # the only kind of module that may import machine / rp2


@pytest.mark.parametrize("name", MODULES)
def test_compiles_with_mpy_cross_armv6m(name, tmp_path) -> None:
    out = tmp_path / (name[:-3] + ".mpy")
    proc = subprocess.run([bundle.mpy_cross(), "-march=armv6m", "-o", str(out), str(FW / name)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert out.stat().st_size > 0


def _imports(tree: ast.AST) -> set[str]:
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("name", MODULES)
def test_only_hals_touch_hardware(name) -> None:
    tree = ast.parse((FW / name).read_text())
    hw = _imports(tree) & {"machine", "rp2", "pyb", "esp32"}
    if name in HARDWARE:
        assert hw
    else:
        assert not hw, f"{name} imports {hw}"


OWN = ["fixmath", "controller", "sensors", "motor", "supervisor", "timing", "app", "appparams", "appstatus", "appstore",
       "apptable", "board", "link_serial", "pacer", "main",
       "gains"]


@pytest.mark.parametrize("mod", OWN)
def test_imports_under_cpython_and_runs_nothing_at_import(mod) -> None:
    m = importlib.import_module(f"firmware.{mod}")
    tree = ast.parse(Path(m.__file__).read_text())
    for node in tree.body:
        # only imports, the const shim, constant assignments, defs and classes
        ok = isinstance(node, (ast.Import, ast.ImportFrom, ast.FunctionDef, ast.ClassDef, ast.Try, ast.Assign, ast.Expr))
        assert ok, f"{mod}: {ast.dump(node)[:80]}"
        if isinstance(node, ast.Assign):
            v = node.value
            assert isinstance(v, (ast.Constant, ast.Tuple, ast.Call, ast.UnaryOp)), f"{mod}: {ast.dump(node)[:80]}"
            if isinstance(v, ast.Call):
                assert isinstance(v.func, ast.Name) and v.func.id == "const", f"{mod}: call at import"
        if isinstance(node, ast.Expr):
            assert isinstance(node.value, ast.Constant)  # a docstring at most


@pytest.mark.parametrize("mod", OWN)
def test_no_floats_in_the_firmware(mod) -> None:
    tree = ast.parse((FW / f"{mod}.py").read_text())
    floats = [n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, float)]
    assert not floats, f"{mod}: float literals {floats}"
    bad = [n for n in ast.walk(tree) if isinstance(n, ast.BinOp) and isinstance(n.op, ast.Div)]
    assert not bad, f"{mod}: true division (float result)"


def test_boot_counter_persists_and_wraps(tmp_path) -> None:
    from firmware.main import boot_count

    f = tmp_path / "boot_count"
    assert [boot_count(str(f)) for _ in range(3)] == [1, 2, 3]
    f.write_text("255")
    assert boot_count(str(f)) == 0
    f.write_text("garbage")
    assert boot_count(str(f)) == 1


def test_bundle(tmp_path) -> None:
    assert bundle.main(["--arch", "armv6m", "--out", str(tmp_path / "fw")]) == 0
    files = {p.name for p in (tmp_path / "fw" / "firmware").iterdir()}
    assert {"app.mpy", "controller.mpy", "gains.mpy", "hal_pico.mpy", "main.mpy", "__init__.py"} <= files
    # one bundle, every use: the HIL main is in it (MODE hil, firmware/main.py); the unix port's pty is not
    assert {"hal_hil.mpy", "main_hil.mpy", "link_usb.mpy"} <= files and "uart_unix.mpy" not in files
    assert "firmware.main" in (tmp_path / "fw" / "main.py").read_text().replace("from firmware import main", "firmware.main")
    with pytest.raises(ValueError):
        bundle.compile_module(FW / "app.py", tmp_path / "x.mpy", arch="z80")
