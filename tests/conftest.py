"""What every test shares: the markers' requirements, written once.

* ``rp2040`` (the emulated Pico): skipped with the reason when node, rp2040js or the MicroPython
  RP2040 image is missing, and always ``slow`` -- booting the emulated board alone takes seconds
  of wall time (it runs at 0.1-0.2x real time), so ``pytest -m "not slow"`` never waits for one.
* ``wasm`` (the MicroPython WebAssembly port under node): skipped with the reason when it is
  not installed.
* ``long`` (minutes; left out of ``make test``) is ``slow`` too, so ``-m "not slow"`` (which
  replaces the default ``-m 'not long'``) leaves it out as well.

One test body on every interpreter it applies to: a test that takes the ``interp`` fixture runs
once per interpreter -- ``cpython`` (in-process), ``unix`` (the 64-bit unix port), ``wasm`` (the
32-bit WebAssembly port, marked ``wasm``), ``rp2040`` (the emulated Pico's raw REPL, marked
``rp2040``, so skipped when missing and ``slow``) -- or over the ones its ``interps`` marker names
(``@pytest.mark.interps("cpython", "unix")``).  ``interp`` is a ``fwharness.Interp``:
``interp.run(code, timeout)`` runs a firmware snippet there and returns what it printed,
``interp.name`` says where, ``interp.alloc_run`` is that port's allocation probe.  The emulated
board behind ``rp2040`` boots once for the session (``emulated_repl``: seconds of wall time) and
each run starts from cleared globals.

The test helpers live in modules of this folder, imported by name (the folder is on the path):
``fwharness`` (the firmware run in an interpreter: the stand-in HAL ``StandInHal``/``FAKE_HAL``,
print-and-parse ``CHK_SRC``/``parse_ints``, allocation probes), ``proto_helpers`` (the protocol's
boards and bridges), ``hil_probe``, ``mpy_proto_board``, ``tool_helpers`` (the board tools' summary
line, the dashboard's HTTP requests).  Which test covers which behaviour:
``tests/README.md``.
"""

from __future__ import annotations

import functools
import shutil
from typing import TYPE_CHECKING, Iterator

import pytest

# the shared checks in the helper modules report their values as the tests' own asserts do
pytest.register_assert_rewrite("fwharness", "tool_helpers")

import fwharness as H  # noqa: E402

if TYPE_CHECKING:
    from host.boards.rp2040.board import EmulatedBoard

# the marker each interpreter's runs carry (their requirements: pytest_collection_modifyitems)
_INTERP_MARKS = {"wasm": pytest.mark.wasm, "rp2040": pytest.mark.rp2040}


@functools.lru_cache(maxsize=None)
def rp2040_missing() -> str | None:
    """Why the emulated RP2040 cannot run here (``None``: it can)."""
    from host.boards.rp2040.board import FIRMWARE, ROOT

    if shutil.which("node") is None:
        return "node not installed"
    if not (ROOT / "node_modules" / "rp2040js").is_dir():
        return "rp2040js not installed (make setup)"
    if not FIRMWARE.is_file():
        return "MicroPython RP2040 image missing (make rp2040)"
    return None


@functools.lru_cache(maxsize=None)
def wasm_missing() -> str | None:
    """Why the MicroPython WebAssembly port cannot run here (``None``: it can)."""
    from host.boards.mpyrun import wasm_available

    return None if wasm_available() else "node / MicroPython WebAssembly port not installed"


@pytest.hookimpl(tryfirst=True)  # before `-m` deselects: an rp2040 test is slow
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if item.get_closest_marker("long") is not None and item.get_closest_marker("slow") is None:
            item.add_marker(pytest.mark.slow)
        if item.get_closest_marker("rp2040") is not None:
            if item.get_closest_marker("slow") is None:
                item.add_marker(pytest.mark.slow)
            why = rp2040_missing()
            if why:
                item.add_marker(pytest.mark.skip(reason=why))
        if item.get_closest_marker("wasm") is not None:
            why = wasm_missing()
            if why:
                item.add_marker(pytest.mark.skip(reason=why))


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    # a test taking `interp` runs once per interpreter (its `interps` marker's, else all), each
    # run carrying its interpreter's marker
    if "interp" not in metafunc.fixturenames:
        return
    m = metafunc.definition.get_closest_marker("interps")
    names = m.args if m is not None else H.INTERPRETERS
    bad = [n for n in names if n not in H.INTERPRETERS]
    if bad:
        raise pytest.UsageError(f"{metafunc.definition.nodeid}: unknown interpreters {bad}")
    metafunc.parametrize("interp", [pytest.param(n, id=n, marks=_INTERP_MARKS.get(n, ())) for n in names],
                         indirect=True)


@pytest.fixture(scope="session")
def emulated_repl(tmp_path_factory: pytest.TempPathFactory) -> Iterator["EmulatedBoard"]:
    """The emulated Pico booted to its REPL with the ``make firmware`` bundle importable, once
    for the session (the board's own ``main.py`` empty)."""
    from host.boards.rp2040.board import EmulatedBoard, build_bundle

    bundle = build_bundle(tmp_path_factory.mktemp("bundle"))
    with EmulatedBoard(bundle, main=False) as b:
        yield b


@pytest.fixture
def interp(request: pytest.FixtureRequest) -> H.Interp:
    """The interpreter of this run (``request.param``, from :func:`pytest_generate_tests`)."""
    name = request.param
    board = request.getfixturevalue("emulated_repl") if name == "rp2040" else None
    return H.Interp(name, board)
