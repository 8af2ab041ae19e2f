"""The command line agrees with itself (issue 22 item 4): one option name per concept (old
spellings kept as aliases), ``--port`` everywhere, what the host's tables know refused on the
host, gain files read as data, a frozen robot's logs warned about and refused -- in one line.

No board is needed: every refusal here happens before a port is opened (a port that does not
exist would fail with status 1, not 2)."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest

from host.cli import main as cli

ROOT = Path(__file__).resolve().parent.parent
NO_PORT = "/dev/upright-no-such-port"


def _run(capsys: pytest.CaptureFixture[str], argv: list[str]) -> tuple[int, str, str]:
    try:
        rc = cli.main(argv)
    except SystemExit as exc:
        rc = int(exc.code or 0)
    cap = capsys.readouterr()
    return rc, cap.out, cap.err.strip()


@pytest.mark.parametrize("argv", [
    ["board", "--port", "X", "--baudrate", "9600", "status"],
    ["board", "--port", "X", "--baud", "9600", "status"],          # the old spelling
    ["proto", "dump", "--baud", "9600"],
    ["proto", "dump", "--baudrate", "9600"],
    ["hil", "--port", "X", "--baud", "9600"],
    ["hil", "--port", "X", "--baudrate", "9600"],
    ["dashboard", "--port", "X", "--baudrate", "9600"],
])
def test_one_name_for_the_line_rate(argv: list[str]) -> None:
    args = cli.build_parser(only=argv[0]).parse_args(argv)
    assert args.baudrate == 9600


def test_proto_dump_takes_port_like_every_tool(capsys) -> None:
    rc, out, err = _run(capsys, ["proto", "dump", "--port", "loop://", "--duration", "0.2"])
    assert rc == 0, err
    rc, out, err = _run(capsys, ["proto", "dump", "loop://", "--duration", "0.2"])  # positional kept
    assert rc == 0, err
    rc, _, err = _run(capsys, ["proto", "dump", "loop://", "--port", "/dev/ttyACM0"])
    assert rc == 2 and len(err.splitlines()) == 1 and "give one" in err, err


def test_params_list_needs_no_board(capsys) -> None:
    rc, out, err = _run(capsys, ["board", "params", "list"])  # no --port at all
    assert rc == 0, err
    rows = {ln.split()[0]: ln for ln in out.splitlines()}
    assert "max_duty" in rows and "[read-only]" in rows["loop_rate_hz"]
    assert "[read-only]" not in rows["max_duty"]
    rc, _, err = _run(capsys, ["board", "status"])
    assert rc == 2 and "--port is required" in err


def test_read_only_parameter_refused_on_the_host(capsys) -> None:
    rc, _, err = _run(capsys, ["board", "--port", NO_PORT, "params", "set", "loop_rate_hz", "1000"])
    assert rc == 2 and len(err.splitlines()) == 1, err  # 2: refused before the port (1 if opened)
    assert "loop_rate_hz is read-only" in err and "gain table" in err, err


def test_gains_file_and_design_conflict_reported_first(capsys, tmp_path) -> None:
    bad = tmp_path / "broken.py"
    bad.write_text("FLAT = (1, 2,\n")  # a syntax error that must not be what the user hears
    rc, _, err = _run(capsys, ["board", "--port", NO_PORT, "gains", "upload", str(bad), "--design"])
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert "not both" in err and "SyntaxError" not in err, err
    rc, _, err = _run(capsys, ["board", "--port", NO_PORT, "gains", "upload", str(bad)])
    assert rc == 2 and "SyntaxError line" in err, err


@pytest.mark.slow
def test_gain_module_is_read_as_data_never_run(tmp_path) -> None:
    from host.operate.board import ParamInputError, gains_blob_from_design, gains_blob_from_file

    marker = tmp_path / "ran"
    mod = tmp_path / "evil.py"
    mod.write_text(f"open({str(marker)!r}, 'w').write('x')\nFLAT = (1, -2, 3)\n")
    blob = gains_blob_from_file(mod)
    assert blob == (1).to_bytes(4, "little") + (-2).to_bytes(4, "little", signed=True) + (3).to_bytes(4, "little")
    assert not marker.exists()  # the statement before FLAT was parsed, not executed
    computed = tmp_path / "computed.py"
    computed.write_text("FLAT = [1] * 3\n")
    with pytest.raises(ParamInputError, match="not a literal list of ints"):
        gains_blob_from_file(computed)
    # what `upright export --out` writes reads back to the design's own blob
    out = tmp_path / "gains.py"
    p = subprocess.run([sys.executable, "-m", "host.cli.main", "export", "--out", str(out)], cwd=ROOT,
                       capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert p.returncode == 0, p.stderr
    assert gains_blob_from_file(out) == gains_blob_from_design()[0]


def test_excite_arm_is_deprecated_with_a_note(capsys, tmp_path) -> None:
    rc, _, err = _run(capsys, ["board", "--port", NO_PORT, "excite", "--arm", "--out", str(tmp_path / "x.csv")])
    assert rc == 1, err  # the port does not exist: the run fails after the note
    assert "--arm is deprecated and does nothing" in err.splitlines()[0], err
    rc, _, err = _run(capsys, ["board", "--port", NO_PORT, "excite", "--out", str(tmp_path / "x.csv")])
    assert "deprecated" not in err


@pytest.mark.parametrize("action", ["log", "excite", "arm"])
def test_seconds_is_documented_as_wall_time(capsys, action) -> None:
    rc, out, _ = _run(capsys, ["board", "--port", "X", action, "--help"])
    assert rc == 0
    assert "wall-clock" in " ".join(out.split()), out


def _frozen_log(path: Path, rows: int = 600) -> None:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "seq", "x", "xdot", "phi", "phidot", "ref", "force", "duty", "step_us", "state", "faults",
                    "excite", "exc_amp_n", "exc_div"])
        for i in range(rows):
            w.writerow([i * 0.002, (2 * i) % 256, 0.0, 0.0, 0.0, 0.0, 0.0, 0.5 if i % 8 < 4 else -0.5,
                        1000 if i % 8 < 4 else -1000, 300, 3, 0, 1, 0.5, 4])


@pytest.mark.slow
def test_identify_refuses_a_log_where_nothing_moved(tmp_path) -> None:
    log = tmp_path / "bal.csv"
    _frozen_log(log)
    p = subprocess.run([sys.executable, "-m", "host.cli.main", "identify", str(log)], cwd=ROOT, capture_output=True,
                       text=True, timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT)})
    err = p.stderr.strip()
    assert p.returncode == 2 and len(err.splitlines()) == 1, err
    assert "nothing moved" in err and str(log) in err, err
    for noise in ("SVD", "Warning", "LAPACK", "Traceback"):
        assert noise not in err + p.stdout, err


class _Msg:
    def __init__(self, name: str, **phys: float) -> None:
        self.NAME = name
        self._p = phys

    def physical(self) -> dict:
        return self._p


class _Board:
    def __init__(self) -> None:
        self.listeners: list = []


def _tick(board: _Board, seq: int, x: float, phi: float) -> None:
    for fn in list(board.listeners):
        fn(_Msg("telem_state", x=x, xdot=0.0, phi=phi, phidot=0.0), seq, 0.01 * seq)
        fn(_Msg("telem_ctrl", ref=0.0, force=0.0, duty=0, step_us=100), seq, 0.01 * seq)


def test_recorder_says_whether_anything_moved(tmp_path) -> None:
    from host.operate.record import Recorder

    b = _Board()
    rec = Recorder(b, tmp_path / "r.csv")
    assert rec.moved() is None
    for k in range(5):
        _tick(b, k, 0.0, 0.01)
    assert rec.moved() is False
    _tick(b, 5, 0.0, 0.0105)  # one count of the pot is movement
    assert rec.moved() is True
    rec.reset_span()
    _tick(b, 6, 0.2, 0.0)
    _tick(b, 7, 0.2, 0.0)
    assert rec.moved() is False
    rec.close()


def test_uptime_says_where_it_wraps() -> None:
    from host.cli.board import _field, uptime_text

    f = _field("uptime_ms", "heartbeat")  # the heartbeat's own field (SESSION's is 32 bits)
    text = uptime_text({"heartbeat": {"uptime_ms": 1900}, "identity": {}})
    if f.size == 2:  # the heartbeat's 16-bit field: 65 s after boot must not read as a reboot
        assert text == "uptime 1.9 s (mod 65.5 s: the board sends its low 16 bits)", text
    else:
        assert text.startswith("uptime 1.9 s") and "mod" not in text, text
    assert uptime_text({"heartbeat": {}, "identity": {}}) == "uptime -"


class _Sc:
    def __init__(self, name: str, duration: float) -> None:
        self.name, self.duration = name, duration


def test_hil_plan_estimates_up_front_and_per_scenario(monkeypatch) -> None:
    import io

    import host.cli.hil as H

    clock = [100.0]
    monkeypatch.setattr(H.time, "perf_counter", lambda: clock[0])
    buf = io.StringIO()
    plan = H.Plan([_Sc("a", 2.0), _Sc("b", 6.0)], 500.0, stream=buf)
    assert "2 scenario(s), 8 s of robot time (4,000 control ticks)" in plan.header()
    plan("a", 0, 1000)
    clock[0] += 10.0  # 100 ticks/s
    plan("a", 1000, 1000)
    plan("b", 0, 3000)
    clock[0] += 10.0
    plan("b", 1000, 3000)
    out = buf.getvalue()
    assert "[1/2] a: 1000 ticks" in out and "[2/2] b: 3000 ticks" in out, out
    assert "estimate: 40 s in all at 100 ticks/s (30 s left)" in out, out
    assert "[2/2] b: 33% (1000/3000 ticks), ~20 s left" in out, out
    # the step-time column says what it measures
    assert "not a 100 % load" in H.STEP_NOTE


def test_status_prefers_the_boards_full_uptime_and_names_loop_starts() -> None:
    from host.cli.board import render_status, uptime_text

    st = {"heartbeat": {"uptime_ms": 1900}, "identity": {}, "board_status": {"uptime_ms": 67436, "starts": 2,
                                                                             "cfg_slot": 1, "cfg_seq": 7}}
    assert uptime_text(st) == "uptime 67.4 s"  # not "1.9 s": the 16-bit heartbeat field wrapped once
    full = {"port": "p", "identity": {}, "heartbeat": st["heartbeat"], "state": "disarmed", "faults": 0,
            "heartbeat_hz": 10.0, "link": {"sent": 1, "received": 1, "drops": {}}, "board_stats": {},
            "board_status": st["board_status"]}
    text = render_status(full)
    assert "started 2 time(s) since boot (MODE switches back to the robot, no reset)" in text, text
    assert "saved configuration: copy b, sequence 7" in text, text
