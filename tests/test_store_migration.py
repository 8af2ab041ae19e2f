"""A firmware update keeps the calibration (issue 27 follow-up): a configuration saved by an older
firmware -- gain-table layout version 1, 114 ints, before the EST field -- is no longer CORRUPT
(defaults, F_CONFIG, pot offset and signs lost) but loads its parameters: the table converted to
the current layout (``cfg_status`` 4 *migrated*, firmware/store.py ``UPGRADES``) or, when no step
converts it, dropped for the firmware's own (5 *params only*).  CPython, and the MicroPython unix
port (the real interpreter booting an App on the v1 copy)."""

from __future__ import annotations

from pathlib import Path

import pytest

from firmware import gains as G
from firmware import msgtable as T
from firmware.app import App
from firmware.store import CORRUPT, LOADED, MIGRATED, NAMES, PARAMS_ONLY, UPGRADES, ConfigStore, encode, upgrade
from firmware.supervisor import F_CONFIG
import fwharness as H
from host.boards.mpyrun import run_unix

V1_LEN = 114


def v1_table() -> list[int]:
    """The shipped table as the version-1 firmware stored it: no EST (the last field), header
    version 1 and length 114."""
    t = list(G.FLAT[:V1_LEN])
    t[0], t[2] = 1, V1_LEN
    return t


def calibrated_params() -> list[int]:
    """The parameters of a commissioned robot: every one moved off its default, in range (but
    the loop rate, which reports the active table's)."""
    app = App(H.StandInHal(inc=2000), config={})
    p = list(app.params)
    for q in T.PARAMS:
        k, lo, hi = q[0], q[3], q[4]
        if k == T.P_LOOP_RATE:
            continue
        v = p[k] + 1 if p[k] + 1 <= hi else p[k] - 1
        assert lo <= v <= hi
        p[k] = v
    return p


def _boot(d: Path) -> tuple[App, int]:
    app = App(H.StandInHal(inc=2000), config={})
    return app, app.attach_store(ConfigStore(str(d)))


def test_upgrade_steps_match_the_gain_table_layout() -> None:
    # version 1 is version 2 without EST, which is the last field: the one step UPGRADES knows
    names = [n for n, _ in G.LAYOUT]
    assert G.VERSION == 2 and names[-1] == "EST" and G.LENGTH == V1_LEN + 1
    assert UPGRADES == ((1, V1_LEN, V1_LEN, (0,)),)
    t = upgrade(v1_table(), G.VERSION, G.LENGTH)
    assert t == list(G.FLAT[:V1_LEN]) + [0] and t[:3] == [G.VERSION, G.DELAY, G.LENGTH]
    assert upgrade(list(G.FLAT), G.VERSION, G.LENGTH) == list(G.FLAT)  # already current
    assert upgrade([7, 5, 100] + [0] * 97, G.VERSION, G.LENGTH) is None  # unknown layout


def test_v1_copy_keeps_params_and_table_migrated(tmp_path: Path) -> None:
    p = calibrated_params()
    t1 = v1_table()
    (tmp_path / NAMES[0]).write_bytes(bytes(encode(3, p, t1)))
    app, st = _boot(tmp_path)
    assert st == MIGRATED and app.status_get(T.S_CFG_STATUS) == MIGRATED
    assert app.sup.faults & F_CONFIG == 0 and not app.config_bad
    assert list(app.params) == p  # the calibration survived the update
    assert list(app.table) == list(G.FLAT[:V1_LEN]) + [0]
    assert app.status_get(T.S_CFG_SLOT) == 0 and app.status_get(T.S_CFG_SEQ) == 3
    # the next save writes the current layout into the other slot; the old copy stays untouched
    old = (tmp_path / NAMES[0]).read_bytes()
    app.store.save(app.params, app.table)
    assert (tmp_path / NAMES[0]).read_bytes() == old
    app2, st2 = _boot(tmp_path)
    assert st2 == LOADED and app2.status_get(T.S_CFG_SEQ) == 4 and list(app2.params) == p


def test_unconvertible_old_table_keeps_params_only(tmp_path: Path) -> None:
    p = calibrated_params()
    t = [9, 5, 60] + [1] * 57  # a layout no step converts
    (tmp_path / NAMES[1]).write_bytes(bytes(encode(5, p, t)))
    app, st = _boot(tmp_path)
    assert st == PARAMS_ONLY and app.sup.faults & F_CONFIG == 0
    assert list(app.params) == p and list(app.table) == list(G.FLAT)


def test_a_v1_table_that_fails_the_check_after_conversion_still_keeps_the_params(tmp_path: Path) -> None:
    p = calibrated_params()
    t1 = v1_table()
    t1[1] = G.DELAY + 1  # another delay: the converted table fails validate
    (tmp_path / NAMES[0]).write_bytes(bytes(encode(2, p, t1)))
    app, st = _boot(tmp_path)
    assert st == PARAMS_ONLY and list(app.params) == p and list(app.table) == list(G.FLAT)


def test_old_layout_with_bad_params_and_own_layout_with_bad_table_stay_corrupt(tmp_path: Path) -> None:
    p = calibrated_params()
    q = T.PARAMS[0]
    bad = list(p)
    bad[q[0]] = q[4] + 1  # out of range
    (tmp_path / NAMES[0]).write_bytes(bytes(encode(1, bad, v1_table())))
    # our own length with a table failing the check: CORRUPT as before
    (tmp_path / NAMES[1]).write_bytes(bytes(encode(2, p, list(G.FLAT[:3]) + [0] * (G.LENGTH - 3))))
    app, st = _boot(tmp_path)
    assert st == CORRUPT and app.sup.faults & F_CONFIG and list(app.params) != p


def test_newest_copy_wins_whatever_its_status(tmp_path: Path) -> None:
    p = calibrated_params()
    app, _ = _boot(tmp_path)
    s = ConfigStore(str(tmp_path), T.N_PARAMS, G.LENGTH)
    s.seq, s.slot = 6, 1
    s.save(list(app.params), list(G.FLAT))  # slot 0, seq 7: a current copy, default params
    (tmp_path / NAMES[1]).write_bytes(bytes(encode(6, p, v1_table())))  # older v1 copy
    app2, st = _boot(tmp_path)
    assert st == LOADED and app2.status_get(T.S_CFG_SEQ) == 7 and list(app2.params) != p
    (tmp_path / NAMES[1]).write_bytes(bytes(encode(8, p, v1_table())))  # newer v1 copy
    app3, st3 = _boot(tmp_path)
    assert st3 == MIGRATED and app3.status_get(T.S_CFG_SEQ) == 8 and list(app3.params) == p


UNIX = H.FAKE_HAL + """
from firmware import msgtable as T
from firmware import gains as G
from firmware.app import App
from firmware.store import ConfigStore, encode
d = '@@DIR@@'
P = @@P@@
T1 = list(G.FLAT[:114]); T1[0] = 1; T1[2] = 114
with open(d + '/cfg_a.bin', 'wb') as f:
    f.write(encode(3, P, T1))
app = App(Hal(), config={'epoch': 0})
st = app.attach_store(ConfigStore(d))
print('boot', st, app.status_get(T.S_CFG_STATUS), app.sup.faults, app.sup.state)
print('params', 1 if list(app.params) == P else 0)
print('table', 1 if list(app.table) == list(G.FLAT[:114]) + [0] else 0, app.table[114])
"""


def test_unix_port_boots_a_v1_copy_with_its_calibration(tmp_path: Path) -> None:
    code = UNIX.replace("@@DIR@@", str(tmp_path)).replace("@@P@@", repr(calibrated_params()))
    out = run_unix(code)
    lines = {ln.split()[0]: ln.split()[1:] for ln in out.strip().splitlines() if ln.strip()}
    assert lines["boot"][:2] == [str(MIGRATED), str(MIGRATED)], out
    assert int(lines["boot"][2]) & F_CONFIG == 0, out
    assert lines["params"] == ["1"] and lines["table"] == ["1", "0"], out


# ---------------------------------------------------------------- the emulated RP2040
@pytest.mark.slow
@pytest.mark.rp2040
def test_emulated_board_boots_a_v1_copy_with_its_calibration(tmp_path: Path) -> None:
    """The flashed firmware (main.py, HalPico, LittleFS) powering up on a flash whose
    configuration the version-1 firmware saved: the calibration is there, read over the link."""
    from host.boards.rp2040.board import EmulatedBoard, build_bundle
    from host.hil.emulated import EmulatedHil
    from host.link import messages as M

    p = [q[5] for q in T.PARAMS]
    p[T.P_TILT_LIMIT] = 321
    p[T.P_POT_OFFSET] = 2100
    p[T.P_ADC_SIGN] = -1
    p[T.P_MOTOR_SIGN] = -1
    blob = bytes(encode(3, p, v1_table()))
    with EmulatedBoard(build_bundle(tmp_path / "bundle"), main=True, files={NAMES[0]: blob}) as b:
        b.set_adc(2100)
        h = EmulatedHil(board=b).open()
        h._idle(20_000.0)

        def get(i: int) -> int:
            return int(h.request(M.ParamGet(index=i)).value)

        st = [get(T.STATUS_BASE + k) for k in (T.S_CFG_STATUS, T.S_CFG_SLOT, T.S_CFG_SEQ)]
        got = [get(q[0]) for q in T.PARAMS]
        faults = int(h.request(M.Request(msg_id=T.HEARTBEAT)).faults)
    assert st == [MIGRATED, 0, 3], st
    assert got == p, got
    assert faults & F_CONFIG == 0, faults
