"""Issue 7, bad commands and gain uploads, in the HIL loop (lockstep, real firmware under MicroPython).

"Changes nothing" is shown by the strongest test lockstep allows: the same scenario run
again after (or with, mid-run) the refused commands gives a bit-identical motor command
trace; a positive control (a different table actually applied) shows that the comparison
can fail.  The decoder/dispatcher fuzzing (hypothesis in make test, 1.2 M heap-locked
inputs in make bench) is P's: tests/test_proto_commands.py, tests/test_proto_mpy.py and
host/bench/proto.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from firmware import msgtable as T
from firmware.supervisor import BALANCING
from host.link import messages as M
from host.design.export import export
from host.hil.faults import StreamFaults
from host.hil.lossy import run_lossy
from host.hil.session import HilSession
from host.link.clients import CommandRefused
from sim.scenario import scenario_from_dict

SCEN = scenario_from_dict({"name": "gains_probe", "duration": 1.0, "initial": {"phi": 0.08}})
NAMES = {p[0]: p[1] for p in T.PARAMS}


def _tables() -> tuple[bytes, bytes]:
    fd = export()
    good = fd.blob()
    fd.tables["MOT"] = [int(fd.tables["MOT"][0] * 1.25)] + list(fd.tables["MOT"][1:])
    return good, fd.blob()


GOOD, ALT = _tables()


@pytest.fixture(scope="module", params=["serial", "can"])
def board(request):
    with HilSession(link=request.param) as s:
        s.link.disarm()
        s.link.upload_gains(GOOD)
        yield s


def _trace(board, **kw) -> np.ndarray:
    run = run_lossy(board, SCEN, **kw)
    assert run.stats["lost"] == 0
    return np.stack([run.log["duty_fw"], run.log["fw_state"], run.log["fw_faults"]])


def _req(board, name: str, **fields):
    # an upload belongs to the board's session (its arming token); a commit carries the
    # table's CRC-32 (the test's tables: _COMMIT_CHECK, set by the begin)
    if name == "gains_begin" and "token" not in fields:
        fields["token"] = board.link.session_token(timeout=1.0)
    if name == "gains_commit" and "check" not in fields:
        fields["check"] = _LAST.get("check", 0)
    return board.link.request(M.BY_NAME[name](**fields), timeout=1.0)


_LAST: dict[str, int] = {}


def _begin(board, table: bytes, crc: int | None = None) -> None:
    # gains_begin for this table (commit's check: its CRC-32)
    _LAST["check"] = M.table_check(table)
    _req(board, "gains_begin", nbytes=len(table), crc=M.crc16(table) if crc is None else crc)


def _refused(board, reason: int, name: str, **fields) -> None:
    with pytest.raises(CommandRefused) as e:
        _req(board, name, **fields)
    assert e.value.reason == reason, (name, e.value)


def _chunks(table: bytes):
    n = T.CHUNK_BYTES
    for off in range(0, len(table), n):
        yield off, table[off:off + n].ljust(n, b"\x00")


def test_gain_upload_interrupted_or_corrupted_never_applied(board) -> None:
    base = _trace(board)
    assert np.array_equal(_trace(board), base)  # lockstep is deterministic
    # positive control: the other table, applied, changes the motor commands
    board.link.disarm()
    board.link.upload_gains(ALT)
    alt = _trace(board)
    assert not np.array_equal(alt, base)
    board.link.disarm()
    board.link.upload_gains(GOOD)
    assert np.array_equal(_trace(board), base)

    board.link.disarm()
    # 1. interrupted: half the chunks, then the host goes away; a later commit is refused
    _begin(board, ALT)
    chunks = list(_chunks(ALT))
    for off, data in chunks[: len(chunks) // 2]:
        _req(board, "gains_chunk", offset=off, data=data)
    _refused(board, T.R_INCOMPLETE, "gains_commit")
    # 2. corrupted: every chunk arrives, one byte of the table is wrong -> CRC refuses
    bad = bytearray(ALT)
    bad[len(bad) // 2] ^= 0x10
    _begin(board, ALT)
    for off, data in _chunks(bytes(bad)):
        _req(board, "gains_chunk", offset=off, data=data)
    _refused(board, T.R_BAD_CRC, "gains_commit")
    # 3. a chunk out of order aborts the upload
    _begin(board, ALT)
    _refused(board, T.R_BAD_SEQUENCE, "gains_chunk", offset=12, data=ALT[12:18])
    _refused(board, T.R_BAD_SEQUENCE, "gains_commit")
    # 4. a table with a good CRC but the wrong size / header: the firmware's own check
    short = ALT[:-4]
    _begin(board, short)
    for off, data in _chunks(short):
        _req(board, "gains_chunk", offset=off, data=data)
    _refused(board, T.R_BAD_LENGTH, "gains_commit")
    hdr = bytearray(ALT)
    hdr[0] ^= 0x7F  # table format version
    _begin(board, bytes(hdr))
    for off, data in _chunks(bytes(hdr)):
        _req(board, "gains_chunk", offset=off, data=data)
    with pytest.raises(CommandRefused) as e:
        _req(board, "gains_commit")
    assert e.value.reason in (T.R_BAD_SHAPE, T.R_UNSTABLE), e.value
    # 5. a complete, correct table while the motor runs: refused, upload kept for later
    board.link.arm()
    _begin(board, ALT)
    for off, data in _chunks(ALT):
        _req(board, "gains_chunk", offset=off, data=data)
    _refused(board, T.R_ARMED, "gains_commit")
    board.link.disarm()
    _refused(board, T.R_BAD_LENGTH, "gains_begin", nbytes=0, crc=0)  # a bad begin ends any upload
    # the old table is still the one in force: bit-identical behaviour
    assert np.array_equal(_trace(board), base)


@pytest.mark.slow
def test_gain_upload_over_corrupted_link_applies_all_or_nothing(board) -> None:
    if board.link_kind != "serial":
        pytest.skip("bit errors exist on the serial line only (CAN frames are CRC-checked by the controller)")
    base = _trace(board)
    board.link.disarm()
    board.link.upload_gains(ALT)
    alt = _trace(board)
    board.link.disarm()
    board.link.upload_gains(GOOD)
    from host.hil.session import install_fault as _install_fault

    outcomes = []
    for seed in (1, 2):
        tx = StreamFaults("serial", seed=seed, flip=0.04, drop_byte=0.03, drop=0.03)
        rx = StreamFaults("serial", seed=seed + 100, flip=0.04, drop=0.03)
        inner = board.link._ser
        _install_fault(board.link, tx, rx)
        try:
            try:
                board.link.upload_gains(ALT, timeout=0.2, retries=5)
                outcomes.append("applied")
            except (CommandRefused, OSError) as exc:
                outcomes.append(f"refused: {exc}")
        finally:
            board.link._ser = inner
        board.link.disarm()
        got = _trace(board)
        if outcomes[-1] == "applied":
            assert np.array_equal(got, alt), outcomes
        else:
            assert np.array_equal(got, base) or np.array_equal(got, alt), outcomes
        assert tx.faults.corrupted > 0
        board.link.disarm()
        board.link.upload_gains(GOOD)
    assert "applied" in outcomes, outcomes


def test_commands_out_of_range_or_wrong_state_refused_mid_run_change_nothing(board) -> None:
    before = {i: board.link.param_get(i) for i in NAMES}
    base = _trace(board)
    L = board.link
    bad = [
        (M.BY_NAME["set_reference"](x_um=before[T.P_REF_LIMIT] + 1), T.R_OUT_OF_RANGE),
        (M.BY_NAME["set_reference"](x_um=-(1 << 30) + 1), T.R_OUT_OF_RANGE),
        (M.BY_NAME["param_set"](index=T.P_TILT_LIMIT, value=5), T.R_OUT_OF_RANGE),
        (M.BY_NAME["param_set"](index=T.P_WATCHDOG_MS, value=10**6), T.R_OUT_OF_RANGE),
        (M.BY_NAME["param_set"](index=T.P_MAX_DUTY, value=-1), T.R_OUT_OF_RANGE),
        (M.BY_NAME["param_set"](index=T.N_PARAMS + 3, value=1), T.R_BAD_INDEX),
        (M.BY_NAME["param_get"](index=200), T.R_BAD_INDEX),
        # the period comes only from the gain table's RATE (issue 13): read-only in every state
        (M.BY_NAME["param_set"](index=T.P_LOOP_RATE, value=400), T.R_READ_ONLY),
        (M.BY_NAME["clear_faults"](), T.R_BAD_STATE),  # while balancing
        # while balancing a commit is refused before anything else is looked at (bounded work)
        (M.BY_NAME["gains_commit"](check=0), T.R_ARMED),
        # what would tip the balancing robot: refused while armed (issue 23)
        (M.BY_NAME["param_set"](index=T.P_MOTOR_SIGN, value=-1), T.R_ARMED),
        (M.BY_NAME["param_set"](index=T.P_POT_OFFSET, value=100), T.R_ARMED),
        # a corrupted command that moves the cart: its integrity check fails
        (M.BY_NAME["set_reference"](x_um=0, check=1), T.R_BAD_CHECK),
        (M.BY_NAME["gains_chunk"](offset=0, data=b"\x01" * 6), T.R_BAD_SEQUENCE),
        (M.BY_NAME["request"](msg_id=T.ARM), T.R_NOT_SUPPORTED),
        (M.BY_NAME["heartbeat"](**{f.name: 0 for f in M.BY_NAME["heartbeat"].FIELDS}), T.R_UNKNOWN),  # wrong direction
        (M.BY_NAME["hil_actuator"](tick=0, duty=32767, state=BALANCING, faults=0), T.R_UNKNOWN),
    ]

    def inject(k: int) -> None:
        if k == 300:  # balancing by now
            for msg, _ in bad:
                L.send(msg)

    run = run_lossy(board, SCEN, on_tick=inject)
    got = np.stack([run.log["duty_fw"], run.log["fw_state"], run.log["fw_faults"]])
    nacks = [(m.msg_id, m.reason) for _, m in run.stats["replies"] if m.NAME == "nack"]
    want = [(msg.ID, reason) for msg, reason in bad]
    assert sorted(nacks) == sorted(want), (nacks, want)
    assert not [m for _, m in run.stats["replies"] if m.NAME != "nack"]
    assert np.all(run.log["fw_state"][300:] == BALANCING)
    # nothing changed: the same motor commands, tick for tick, and the same parameters
    assert np.array_equal(got, base)
    assert {i: L.param_get(i) for i in NAMES} == before
    # wrong state outside the run: arming while faulted, clearing while armed
    L.disarm()
    L.arm()
    _refused(board, T.R_BAD_STATE, "clear_faults")
    L.disarm()
