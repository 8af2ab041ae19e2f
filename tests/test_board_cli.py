"""``upright board`` against the virtual board (firmware under the MicroPython unix port, real time).

The board runs on pty A (:class:`host.boards.vport.VirtualBoard`); the command opens pty B; a
relay thread copies bytes between them -- a cable the test can pull (:meth:`Relay.unplug`)
and through which it plays the user's hands in ``calibrate`` (HIL sensor frames: the
pendulum held upright, tilted, the cart rolled).
"""

from __future__ import annotations

import csv
import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

import tool_helpers as TH
from host.boards.vport import PTMX, VirtualBoard, slave_of
from host.link import messages as M

# every test runs an `upright board` process against the virtual board in real time (4-25 s each)
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parent.parent
UPRIGHT = [sys.executable, "-m", "host.cli.main"]


class Relay:
    """Board on pty A, host on pty B, bytes copied both ways until unplugged."""

    def __init__(self) -> None:
        self.fa = os.open(PTMX, os.O_RDWR | os.O_NOCTTY)
        self.board_port = slave_of(self.fa)
        self.fb = os.open(PTMX, os.O_RDWR | os.O_NOCTTY)
        self.port = slave_of(self.fb)
        self.board = VirtualBoard(self.board_port, mode="realtime").start()
        self._lock = threading.Lock()
        self._stop = False
        self.plugged = True
        self._seq = 0
        self._t = threading.Thread(target=self._pump, daemon=True)
        self._t.start()

    def _pump(self) -> None:
        while not self._stop:
            fds = [self.fa] + ([self.fb] if self.plugged else [])
            try:
                r = select.select(fds, [], [], 0.1)[0]
            except (OSError, ValueError):
                return
            for fd in r:
                try:
                    d = os.read(fd, 4096)
                except OSError:
                    continue
                if fd == self.fa:
                    if self.plugged:
                        try:
                            os.write(self.fb, d)
                        except OSError:
                            pass
                else:
                    with self._lock:
                        os.write(self.fa, d)

    def sensors(self, adc: int, enc: int) -> None:
        """The user's hands: the board's next ticks read these sensors."""
        self._seq = (self._seq + 1) & 0xFF
        frame = M.encode_serial(M.BY_NAME["hil_sensor"](tick=0, adc=adc, enc=enc & 0xFFFF), self._seq)
        with self._lock:
            os.write(self.fa, frame)

    def unplug(self) -> None:
        """Pull the cable: the host's end of the pty hangs up."""
        self.plugged = False
        time.sleep(0.15)
        os.close(self.fb)

    def close(self) -> None:
        self._stop = True
        self._t.join(timeout=1)
        os.close(self.fa)
        self.board.stop()
        if self.plugged:
            os.close(self.fb)


@pytest.fixture
def relay():
    r = Relay()
    try:
        yield r
    finally:
        r.close()


def board(r: Relay, *argv: str, timeout: float = 60, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([*UPRIGHT, "board", "--port", r.port, *argv], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout, **kw)


def test_status_json(relay):
    p = board(relay, "status", "--json")
    assert p.returncode == 0, p.stderr
    st = json.loads(p.stdout)
    assert st["state"] == "disarmed"
    assert st["fault_names"] == []
    assert st["identity"].get("table_match", True)
    assert st["heartbeat_hz"] and 5 < st["heartbeat_hz"] < 20  # heartbeat_ms 100
    assert st["link"]["received"] > 0


def test_arm_feeds_watchdog_then_disarms(relay):
    # 1.5 s armed is 6 watchdog periods (250 ms): only the host heartbeat keeps it from a fault
    p = board(relay, "arm", "--seconds", "1.5")
    assert p.returncode == 0, p.stderr
    assert "armed" in p.stderr and "disarmed" in p.stderr
    lines = [ln.strip() for ln in p.stderr.splitlines() if ln.startswith("upright board: ")]
    # while armed it reports armed/balancing, never the stale pre-arm "disarmed" heartbeat
    assert lines[-1] == "upright board: disarmed" and "upright board: disarmed" not in lines[:-1], lines
    assert any(ln in ("upright board: armed", "upright board: balancing") for ln in lines), lines
    st = json.loads(board(relay, "status", "--json").stdout)
    assert st["state"] == "disarmed" and st["faults"] == 0


def test_params_by_name(relay):
    p = board(relay, "params", "set", "max_duty", "9000")
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "max_duty = 9000"
    p = board(relay, "params", "get", "max_duty", "--json")
    assert json.loads(p.stdout) == {"max_duty": 9000}
    bad = board(relay, "params", "set", "no_such_param", "1")
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1
    assert "unknown parameter 'no_such_param'" in bad.stderr
    bad = board(relay, "params", "set", "max_duty", "40000")
    assert bad.returncode == 2 and "outside 0..32767" in bad.stderr


def test_gains_upload_crc_read_back(relay):
    p = board(relay, "gains", "upload")
    assert p.returncode == 0, p.stderr
    assert "verified" in p.stdout


def test_log_csv_rows_match_telemetry(relay, tmp_path):
    out = tmp_path / "run.csv"
    # "N rows (M telemetry frames)": each row is one TELEM_STATE + TELEM_CTRL pair
    rows, line = TH.logged_rows(board(relay, "log", "--seconds", "2", "--out", str(out)), out)
    assert 60 < len(rows) < 140  # 500 Hz / telem_div 10 = 50 rows/s
    assert line.endswith("0 lost")


def test_excite_recorded(relay, tmp_path):
    # the firmware's own PRBS (EXCITE, issue 15 item 4): every tick recorded (telem_div 1 for
    # the run, put back after), the force column +-amplitude around the controller's force
    out = tmp_path / "prbs.parquet"
    p = board(relay, "excite", "--seconds", "2", "--amplitude", "0.5", "--div", "4", "--out", str(out))
    assert p.returncode == 0, p.stderr
    # nobody moves the relay's sensors: the run is recorded, and the user is told it is useless
    warn = [ln for ln in p.stderr.splitlines() if "nothing moved" in ln]
    assert len(warn) == 1 and "upright identify` cannot use this log" in warn[0], p.stderr
    import pyarrow.parquet as pq

    t = pq.read_table(out).to_pydict()
    on = [i for i, m in enumerate(t["excite"]) if m == 1]
    assert len(on) > 400  # 500 rows/s while exciting (telem_div 1)
    assert set(t["exc_amp_n"][i] for i in on) == {0.5} and set(t["exc_div"][i] for i in on) == {4}
    f = [t["force"][i] for i in on[20:]]
    assert max(f) - min(f) > 0.9  # +-0.5 N on a steady balancing force
    p = board(relay, "params", "get", "telem_div", "--json")
    assert json.loads(p.stdout) == {"telem_div": 10}
    bad = board(relay, "excite", "--seconds", "1", "--amplitude", "5", "--out", str(tmp_path / "x.csv"))
    assert bad.returncode == 1 and "out_of_range" in bad.stderr, bad.stderr
    st = json.loads(board(relay, "status", "--json").stdout)
    assert st["state"] == "disarmed"


def test_unplugged_mid_log_keeps_rows(relay, tmp_path):
    out = tmp_path / "cut.csv"
    proc = subprocess.Popen([*UPRIGHT, "board", "--port", relay.port, "log", "--seconds", "20", "--out", str(out)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # unplug once rows are on disk (the tool's start-up -- imports, the board's clock measured -- varies
    # with the load: a fixed sleep sometimes cut it before 20 rows)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and (not out.exists() or len(out.read_text().splitlines()) < 30):
        time.sleep(0.2)
    time.sleep(0.5)
    relay.unplug()
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 1, err
    last = err.strip().splitlines()[-1]
    assert "lost" in last and "kept" in last
    n = int(last.split("kept ")[1].split()[0])
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == n > 20


def test_ctrl_c_disarms_and_exits_130(relay):
    proc = subprocess.Popen([*UPRIGHT, "board", "--port", relay.port, "arm"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 30
    seen = ""
    while "armed;" not in seen and time.monotonic() < deadline:
        seen += proc.stderr.readline()
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, seen + err
    assert "disarmed" in err and "interrupted" in err
    st = json.loads(board(relay, "status", "--json").stdout)
    assert st["state"] == "disarmed"


def test_wrong_port_and_silent_board(tmp_path):
    p = subprocess.run([*UPRIGHT, "board", "--port", "/dev/does-not-exist", "status"], cwd=ROOT,
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 1 and len(p.stderr.strip().splitlines()) == 1
    # a pty with nobody on the other end: no answer
    fd = os.open(PTMX, os.O_RDWR | os.O_NOCTTY)
    try:
        p = subprocess.run([*UPRIGHT, "board", "--port", slave_of(fd), "--answer-timeout", "1", "status"],
                           cwd=ROOT, capture_output=True, text=True, timeout=60)
    finally:
        os.close(fd)
    assert p.returncode == 1 and "no answer" in p.stderr and len(p.stderr.strip().splitlines()) == 1


def test_calibrate_scripted(relay, tmp_path):
    """The user's hands through the relay: upright at 2100 counts, +10 deg = +152 counts
    (270-degree pot, 12 bits), the cart rolled 10 cm = -637 counts (encoder reversed)."""
    out = tmp_path / "robot.toml"
    proc = subprocess.Popen([*UPRIGHT, "board", "--port", relay.port, "calibrate", "--out", str(out), "--no-motor"],
                            cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    lines: list[str] = []
    try:
        lines, _ = TH.answer_prompts(proc, relay, TH.CALIBRATE_HANDS)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = "".join(lines)
    assert proc.returncode == 0, text + proc.stderr.read()
    from sim.params import load_params

    p = load_params(out)
    assert p.pot_offset == 2100
    assert abs(p.enc_cpr - 637 / 0.1 * 2 * 3.141592653589793 * 0.03) < 1.5
    assert abs(p.pot_range - 4.712) < 0.05
    got = json.loads(board(relay, "params", "get", "pot_offset", "adc_sign", "enc_sign", "--json").stdout)
    assert got == {"pot_offset": 2100, "adc_sign": 1, "enc_sign": -1}
