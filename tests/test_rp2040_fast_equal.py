"""The viper and native builds equal the plain code on the emulated RP2040 (32-bit, armv6m .mpy).

The unix port and CPython prove the generated builds (firmware/fastpath.py, fasttick.py)
equal the plain methods bit for bit (tests/test_firmware_fastpath.py,
test_firmware_fasttick.py); a 64-bit port's words never overflow the way a 32-bit board's
small ints could.  Here the same scripts run on the emulated Pico from the bundle
``make firmware`` builds (viper compiled for armv6m), fewer iterations (the emulator runs at
~0.15x real time): the controller step of the three emitters on a closed-loop sequence and
its extremes, and whole Apps tick by tick (App.step against StepV.step).  Every per-tick method
of the viper classes against the plain one runs on the board in test_firmware_fasttick.py (its
``rp2040`` run).  The session's booted board (conftest's ``emulated_repl``).
"""

from __future__ import annotations

import pytest

import fwharness as H
import test_firmware_fastpath as FP
import test_firmware_fasttick as FT
from host.boards.rp2040.board import EmulatedBoard

pytestmark = [pytest.mark.slow, pytest.mark.rp2040]

APP_DIV = 4  # whole apps: 1500 ticks per HAL kind


@pytest.fixture
def board(emulated_repl: EmulatedBoard) -> EmulatedBoard:
    # each test starts from the imports only (fwharness.REPL_CLEAR)
    emulated_repl.exec(H.REPL_CLEAR, timeout=30)
    return emulated_repl


def test_controller_step_of_every_emitter_equal_on_the_board(board: EmulatedBoard) -> None:
    yx, yp, r = FP.seq_with_extremes()
    yx, yp, r = yx[-900:], yp[-900:], r[-900:]  # the end of the run and every extreme
    code = (H.flat_src(FP.FD) + H.ints_src(YX=yx, YP=yp, R=r)
            + "GHB = 4000\nHPX = 1200\nFC = 300\n" + FP.MOTOR + FP.STEPS)  # with the gear-play model on
    out = dict(line.split() for line in board.exec(code, timeout=60).splitlines() if line.strip())
    assert int(out["n"]) == len(yx) and int(out["bad"]) == 0


def test_viper_step_equals_app_step_on_the_board(board: EmulatedBoard) -> None:
    code = FT.APP_EQ.replace("DIV = 1 ", f"DIV = {APP_DIV} ", 1)
    out = board.exec(code, timeout=240)
    lines = dict(line.split(" ", 1) for line in out.splitlines() if line.strip() and not line.startswith(("diff", "faults")))
    assert int(lines["app_ticks"]) == 12000 // APP_DIV
    assert int(lines["states"]) == 4  # disarmed, armed, balancing and fault all reached
    assert int(lines["balancing"]) > 1000 // APP_DIV and int(lines["app_bad"]) == 0, out
