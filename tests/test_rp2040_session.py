"""Across resets of the emulated Pico (main.py as flashed; the flash kept, as a power cycle does):
every boot draws another arming token although the emulated ROSC/urandom repeats at every
power-up (the session seed persisted on the flash, firmware/session.py), an arm captured in an
earlier boot is refused (stale_epoch), the boot counter counts the boots; and a MODE switch
to HIL and back restarts the loop without a reset: boot counter and reset cause unchanged,
uptime continuing, the start counted (status value ``starts``).  About 40-60 s of wall time.
"""

from __future__ import annotations

import pytest

from firmware import msgtable as T
from host.boards.rp2040.board import EmulatedBoard, build_bundle
from host.hil.emulated import EmulatedHil
from host.link import messages as M
from host.link.clients import CommandRefused
from sim.params import load_params

pytestmark = pytest.mark.rp2040  # slow; skipped without the emulated board (tests/conftest.py)

BOOTS = 3


def _status(h: EmulatedHil, k: int) -> int:
    return int(h.request(M.ParamGet(index=T.STATUS_BASE + k)).value)


@pytest.fixture(scope="module")
def boots(tmp_path_factory: pytest.TempPathFactory):
    bundle = build_bundle(tmp_path_factory.mktemp("bundle"))
    out: dict = {"tokens": [], "boot": [], "replays": [], "own": []}
    with EmulatedBoard(bundle, main=True) as b:
        arms: list[M.Message] = []
        for k in range(BOOTS):
            if k:
                b.reset()
            b.set_adc(int(round(load_params().pot_offset)))  # sensors healthy: no fault latched
            h = EmulatedHil(board=b).open()
            h._idle(20_000.0)
            ses = h.request(M.Request(msg_id=T.SESSION))
            hb = h.request(M.Request(msg_id=T.HEARTBEAT))
            out["tokens"].append(ses.token)
            out["boot"].append(hb.boot)
            for a in arms:
                try:
                    h.request(a, retries=0)
                    out["replays"].append("acked")
                except CommandRefused as exc:
                    out["replays"].append(exc.reason)
            # this boot's own arm (positive control), then disarmed again
            arm = M.Arm(epoch=ses.token)
            out["own"].append(h.request(arm).NAME)
            h.request(M.Disarm())
            arms.append(arm)
        # a MODE switch to HIL and back: the loop restarts, the board does not reset
        up0 = _status(h, T.S_UPTIME_MS)
        h.stall_ms = 1e9  # in HIL mode the lockstep main waits for sensor frames: no paced loop
        # the switch imports the HIL main: with the flash-cache model (predicted real timing) its
        # answer takes longer than the 40 ms a command gets
        h.reply_ms = 250.0
        h.request(M.Mode(mode=T.MODE_HIL))
        h._idle(20_000.0)
        h.request(M.Mode(mode=T.MODE_ROBOT))
        h._idle(50_000.0)
        out["after_mode"] = {
            "starts": _status(h, T.S_STARTS), "uptime": _status(h, T.S_UPTIME_MS), "uptime0": up0,
            "boot": h.request(M.Request(msg_id=T.HEARTBEAT)).boot,
            "reset_cause": h.request(M.Request(msg_id=T.VERSION)).reset_cause,
        }
    return out


def test_every_boot_draws_another_token_and_old_arms_are_refused(boots) -> None:
    assert len(set(boots["tokens"])) == BOOTS, boots["tokens"]
    assert boots["own"] == ["ack"] * BOOTS
    assert boots["replays"] == [T.R_STALE_EPOCH] * (BOOTS * (BOOTS - 1) // 2), boots["replays"]
    b = boots["boot"]
    assert [(x - b[0]) & 0xFF for x in b] == list(range(BOOTS)), b  # the boot counter counts


def test_a_mode_switch_restarts_the_loop_without_a_reset(boots) -> None:
    a = boots["after_mode"]
    assert a["starts"] == 2
    assert a["uptime"] > a["uptime0"]
    assert a["boot"] == boots["boot"][-1] and a["reset_cause"] == T.RC_POWER_ON
