"""The README's section "On a real robot", every command as shown, against the virtual robot.

The commands are read from README.md's section (as tests/test_readme_commands.py reads the
whole README) and run in order with ``/dev/ttyUSB0`` replaced by the pty of ONE
``upright emulate rp2040 --pty --plant PLANT`` (the emulated Pico, the simulated robot on its
pins) shared by the module; each is checked for what its step promises.  The robot
(:data:`PLANT`) is the design's with other sensors and friction, so calibration and
identification have something to find.  Where a step asks a person to act (hold the pendulum
upright before ``arm``, take the pendulum off for ``excite --cart-only``, reset the board),
the test asks the robot's hands (:mod:`host.hil.virtual_robot`), as the person would act;
``calibrate`` finds the hands by itself.

Extra flags (the reason next to each in :data:`EXTRA`) only shorten or bound what serves until
Ctrl-C, and give the identification runs enough board time: the emulator runs at 0.1-0.4x real
time and the tools' ``--seconds`` are wall seconds.  No timeout flags: every tool measures the
board's clock and scales its waits by it.  The section's first step, ``upright commission``, runs
last (test_9, on the same robot), one stage per command (``--until STAGE``, then ``--resume``),
with ``--fast``.  Wall time of the module: 4.5-6 minutes on
this 2-core machine with a load average of 8-11 (eight runs: 189-362 s, the last three 189, 209, 209 s), most of
it the identification runs, whose wall time follows the emulator's speed.  Known problems are
expected failures with their reason: issue 23 (``deadline`` latched while a tool talks to a
balancing board), ``hil --port``'s fixed answer time.
"""

from __future__ import annotations

import csv
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from host.boards.rp2040.board import ROOT

pytestmark = pytest.mark.rp2040  # slow; skipped without the emulated board (tests/conftest.py)

UPRIGHT = [sys.executable, "-m", "host.cli.main"]
README = ROOT / "README.md"
SHOWN_PORT = "/dev/ttyUSB0"

# the robot on the pins: the design's, with a pot offset, an encoder and a cart friction of its own
# (a friction of 0.5 N s/m: the cart's coast-down time constant M / b is 1 s, so the coast the
# test records -- 30 s of wall time, 1.5-4 s of board time depending on the machine's load --
# separates the friction from the back-EMF)
PLANT_CHANGES = {"pot_offset": 2010, "enc_cpr": 1100, "b": 0.5}

# README command -> flags added (and why)
EXTRA: dict[str, list[str]] = {
    # serves until Ctrl-C: the test sends SIGINT itself (arm) or bounds it (dashboard)
    "upright dashboard --port /dev/ttyUSB0": ["--http-port", "0", "--seconds", "90"],
    # the two excite runs get --board-seconds (and --board-coast) at test time: the identification
    # needs board seconds, and the emulator runs at 0.05-0.4x real time (BAL_BOARD_S, ...)
    # eight scenarios of 5-8 s by default: minutes each on the emulated board; a 1 s tilt shows the
    # same loop, and --virtual runs it too
    "upright hil --port /dev/ttyUSB0": ["--scenario", "SHORT_TILT", "--no-plots", "--out", "hil_port",
                                        "--json", "hil_port.json"],
}
# no timeout flags: every board tool measures the board's clock when it answers and scales its
# request attempts and waits by it (host/operate/board.py Board.measure_speed, host/hil/answer_time.py)
SLOW: list[str] = []
# board seconds of the identification runs (excite --board-seconds / --board-coast: counted in the
# board's own ticks, whatever the emulator's speed); what upright identify needs at least:
# 5 s balancing, 1.5 s cart-only excitation, 2 s coast-down (host/studies/identify*.py MIN_*)
BAL_BOARD_S = 10.0
CART_BOARD_S = 5.0
COAST_BOARD_S = 3.0
WATCHDOG_MS = 2000  # the board's link watchdog during the identification runs (test_7's reason)
SHORT_TILT = ('name = "short_tilt"\nduration = 1.0\nseed = 1\n[initial]\nphi = 0.05\n'
              '[expect]\nphi_max = "pass"\nsettle = "any"\na_max = "any"\n')


sys.path.insert(0, str(Path(__file__).parent))
from test_readme_commands import ROBOT_COMMANDS as COMMANDS  # noqa: E402 - the section's commands, in order
from test_readme_commands import BOARD_COMMANDS  # noqa: E402 - the table's board commands (proto dump)

RAN: set[str] = set()
IDENT: dict[str, object] = {}


class Robot:
    """``upright emulate rp2040 --pty --plant FILE`` in its own process group, and its hands."""

    def __init__(self, tmp: Path) -> None:
        from sim.params import DEFAULT_PATH

        text = Path(DEFAULT_PATH).read_text()
        for k, v in PLANT_CHANGES.items():
            text, n = re.subn(rf"^{k} = \S+", f"{k} = {v}", text, flags=re.M)
            assert n == 1, k
        self.plant_file = tmp / "plant.toml"
        self.plant_file.write_text(text)
        self.tmp = tmp
        self.env = dict(os.environ, TMPDIR=str(tmp / "tmpdir"))
        (tmp / "tmpdir").mkdir()
        self.proc = subprocess.Popen(UPRIGHT + ["emulate", "rp2040", "--pty", "--plant", str(self.plant_file)],
                                     cwd=tmp, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                     stderr=open(tmp / "emulate.err", "w"), text=True, start_new_session=True,
                                     env=self.env)
        self.port = self.proc.stdout.readline().strip()  # type: ignore[union-attr]
        assert self.port.startswith("/dev/pts/"), (tmp / "emulate.err").read_text()
        from host.hil.hands import find_hands

        t0 = time.monotonic()
        self.hands = None
        while self.hands is None and time.monotonic() - t0 < 30:
            self.hands = find_hands(self.port)
            time.sleep(0.2)
        assert self.hands is not None, (tmp / "emulate.err").read_text()

    def argv(self, cmd: str) -> list[str]:
        """A README command as argv for this robot: the port substituted, :data:`EXTRA` added."""
        assert cmd in COMMANDS, f"README.md's section no longer shows: {cmd}"
        RAN.add(cmd)
        argv = shlex.split(cmd.replace(SHOWN_PORT, self.port))[1:] + EXTRA.get(cmd, [])
        if argv[0] == "board":
            argv[3:3] = SLOW
        if "SHORT_TILT" in argv:
            (self.tmp / "short_tilt.toml").write_text(SHORT_TILT)
            argv[argv.index("SHORT_TILT")] = str(self.tmp / "short_tilt.toml")
        return argv

    def run(self, cmd: str, timeout: float = 300) -> subprocess.CompletedProcess:
        r = subprocess.run(UPRIGHT + self.argv(cmd), cwd=self.tmp, capture_output=True, text=True,
                           timeout=timeout, env=self.env)
        assert r.returncode == 0, f"{cmd}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
        assert "Traceback" not in r.stderr
        return r

    def board(self, *argv: str) -> subprocess.CompletedProcess:
        r = subprocess.run(UPRIGHT + ["board", "--port", self.port, *SLOW, *argv], cwd=self.tmp, capture_output=True,
                           text=True, timeout=120, env=self.env)
        assert r.returncode == 0, r.stderr
        return r

    def speed(self, wall_s: float = 3.0) -> float:
        """The emulator's speed now: board seconds per wall second (the robot's clock)."""
        s0, t0 = self.hands.do("state")["board_s"], time.monotonic()
        time.sleep(wall_s)
        s1, t1 = self.hands.do("state")["board_s"], time.monotonic()
        return max(0.02, (s1 - s0) / (t1 - t0))

    def params(self, *names: str) -> dict:
        return json.loads(self.board("params", "get", *names, "--json").stdout)

    def close(self) -> None:
        if self.hands is not None:
            self.hands.close()
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory):
    r = Robot(tmp_path_factory.mktemp("robot"))
    try:
        yield r
    finally:
        r.close()
    # SIGTERM stops it cleanly: exit 0, no temporary directory, no socket left
    assert r.proc.returncode == 0, (r.tmp / "emulate.err").read_text()
    assert list((r.tmp / "tmpdir").iterdir()) == []
    from host.hil.hands import hands_path

    assert not hands_path(r.port).exists()


@pytest.fixture(scope="module")
def plant(robot: Robot):
    from sim.params import load_params

    return load_params(robot.plant_file)


def test_the_section_shows_every_step() -> None:
    for word in ("status", "calibrate", "params set", "params save", "gains upload", " arm", " log ", "excite",
                 "identify", "dashboard", "upright hil --port", "mode robot"):
        assert any(word in c for c in COMMANDS), (word, COMMANDS)


def test_proto_dump_shows_the_boards_frames(robot: Robot) -> None:
    # the command table's `upright proto dump` (default port /dev/ttyUSB0): the robot's port given
    # positionally, as the command takes it; stopped after 20 messages
    assert BOARD_COMMANDS == ["upright proto dump"], BOARD_COMMANDS
    argv = shlex.split(BOARD_COMMANDS[0])[1:] + [robot.port, "--count", "20", "--duration", "120"]
    r = subprocess.run(UPRIGHT + argv, cwd=robot.tmp, capture_output=True, text=True, timeout=180, env=robot.env)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    assert "heartbeat(" in r.stdout and "state=0" in r.stdout, r.stdout[-2000:]


def test_2_status_shows_disarmed(robot: Robot) -> None:
    r = robot.run("upright board --port /dev/ttyUSB0 status")
    assert "state disarmed" in r.stdout and "faults none" in r.stdout, r.stdout
    assert "(matches this host)" in r.stdout
    # the emulated board is slower than real time: the tool measured it and scaled its requests
    # (0.3 s at full speed) by it
    m = re.search(r"board clock at (0\.\d\d)x the wall's: ([0-9.]+) s per request attempt", r.stderr)
    assert m and float(m.group(2)) == pytest.approx(0.3 / float(m.group(1)), rel=0.1), r.stderr


def test_3_calibrate_finds_the_robots_sensors(robot: Robot, plant) -> None:
    from sim.params import load_params

    r = robot.run("upright board --port /dev/ttyUSB0 calibrate --out robot.toml")
    assert "the virtual robot on" in r.stdout, r.stdout
    cal = load_params(robot.tmp / "robot.toml")
    assert abs(cal.pot_offset - plant.pot_offset) <= 1
    assert abs(cal.pot_range / plant.pot_range - 1) < 0.01  # 10 deg = 152 counts: a count of quantisation
    assert abs(cal.enc_cpr / plant.enc_cpr - 1) < 0.005
    # the signs of the robot (the model's: ADC, encoder and motor all +1), set and saved on the board
    assert robot.params("pot_offset", "adc_sign", "enc_sign", "motor_sign") == {
        "pot_offset": plant.pot_offset, "adc_sign": 1, "enc_sign": 1, "motor_sign": 1}
    assert "motor_sign +1 is right" in r.stdout
    # and nothing latched on the way: the user's next step arms (the wheels coasting into the
    # save's flash write once latched enc_jump: calibrate now waits for them to stop)
    st = json.loads(robot.board("status", "--json").stdout)
    assert st["state"] == "disarmed" and st["faults"] == 0, st


def test_4_params_saved_survive_a_reset(robot: Robot, plant) -> None:
    robot.run("upright board --port /dev/ttyUSB0 params set max_duty 8000")
    robot.run("upright board --port /dev/ttyUSB0 params save")
    boot = json.loads(robot.board("status", "--json").stdout)["heartbeat"]["boot"]
    robot.hands.do("reset")  # the board's reset button: the flash kept
    after = robot.params("max_duty", "pot_offset")
    assert after == {"max_duty": 8000, "pot_offset": plant.pot_offset}
    st = json.loads(robot.board("status", "--json").stdout)
    assert st["state"] == "disarmed" and st["heartbeat"]["boot"] is not None
    del boot


def test_5_gains_designed_for_the_calibration_read_back_by_crc(robot: Robot) -> None:
    r = robot.run("upright board --port /dev/ttyUSB0 gains upload --design --params robot.toml --save")
    m = re.search(r"CRC (0x[0-9a-f]{4}); board reports (0x[0-9a-f]{4}): verified", r.stdout)
    assert m and m.group(1) == m.group(2), r.stdout
    assert "saved on the board" in r.stdout
    st = json.loads(robot.board("status", "--json").stdout)
    assert st["identity"]["gains_crc"] == int(m.group(1), 16)


def test_6_arm_balances_and_ctrl_c_disarms(robot: Robot) -> None:
    # "hold the pendulum upright, then arm": held 30 mrad off upright, let go when the board
    # balances -- the controller must catch it
    robot.hands.do("hold", phi=0.03, until="driving")
    p = subprocess.Popen(UPRIGHT + robot.argv("upright board --port /dev/ttyUSB0 arm"), cwd=robot.tmp,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=robot.env,
                         start_new_session=True)
    try:
        t0 = time.monotonic()
        st = robot.hands.do("state")
        while st["hand"] is not None and time.monotonic() - t0 < 120:
            time.sleep(0.5)
            st = robot.hands.do("state")
        assert st["hand"] is None and st["driving"], st  # let go: the board balances
        b0 = st["board_s"]
        worst = 0.0
        while st["board_s"] - b0 < 2.0:  # two seconds of board time, balancing
            st = robot.hands.do("wait", seconds=0.1)
            assert st["driving"] and not st["lying"], st
            worst = max(worst, abs(st["phi"]))
        assert worst < 0.05 and abs(st["phi"]) < 0.01, (worst, st)
        os.killpg(p.pid, signal.SIGINT)  # Ctrl-C
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 130, err
    assert "balancing" in err and "disarmed" in err, err
    st = json.loads(robot.board("status", "--json").stdout)
    assert st["state"] == "disarmed", st
    robot.run("upright board --port /dev/ttyUSB0 params set max_duty 32767")
    robot.run("upright board --port /dev/ttyUSB0 params save")
    assert robot.params("max_duty") == {"max_duty": 32767}


def test_7_log_has_every_frame(robot: Robot) -> None:
    import pyarrow.parquet as pq

    r = robot.run("upright board --port /dev/ttyUSB0 log --seconds 10 --out run.parquet")
    assert re.search(r"; 0 lost", r.stderr), r.stderr
    t = pq.read_table(robot.tmp / "run.parquet").to_pydict()
    assert len(t["t"]) > 20  # the telemetry while disarmed: a few rows a second
    m = re.search(r"(\d+) rows \((\d+) telemetry frames\)", r.stderr)
    assert m and 2 * int(m.group(1)) == int(m.group(2)) and int(m.group(1)) == len(t["t"]), r.stderr
    # every frame the board sent: the board numbers its periodic frames with one counter, so
    # consecutive rows are 1 apart, or 2 with a heartbeat between them (none lost: the recorder's
    # count of every gap over all periodic frames, above)
    gaps = {(b - a) % 256 for a, b in zip(t["seq"], t["seq"][1:])}
    assert gaps <= {1, 2}, sorted(gaps)


def _truth(plant) -> dict:
    from host.studies.identify import truth_of

    return truth_of(plant)


def _run_excite(robot: Robot, cmd: str) -> subprocess.CompletedProcess:
    # an excitation the virtual robot spoils: `enc_jump` latched at its start (seen in two of the last
    # five balancing runs here, within its first 10 rows; once with the board already in `enc_jump`
    # before the run) -- the robot's quadrature edges and the board's PIO count disagree
    # (host/hil/virtual_robot.py, host/hil/emulated.py PinDrive): an expected failure with its reason;
    # excite itself refuses the log (exit 1, one line) as it must
    r = subprocess.run(UPRIGHT + robot.argv(cmd), cwd=robot.tmp, capture_output=True, text=True, timeout=900,
                       env=robot.env)
    if r.returncode == 1 and "faulted during the excitation (enc_jump" in r.stderr:
        pytest.xfail(f"the virtual robot latched enc_jump: {r.stderr.strip().splitlines()[-1][-200:]}")
    assert r.returncode == 0, f"{cmd}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    assert "Traceback" not in r.stderr
    return r


def _excite_runs(robot: Robot, bal: str, cart: str) -> None:
    r = _run_excite(robot, bal)
    m = re.search(r"; ([0-9.]+) s of board time excited", r.stderr.strip().splitlines()[-1])
    assert m and BAL_BOARD_S <= float(m.group(1)) < BAL_BOARD_S + 0.2, r.stderr[-500:]
    rows = list(csv.DictReader(open(robot.tmp / "bal.csv")))
    # no fault during the excitation -- `deadline` included: a tool asking the balancing board for
    # its state never makes a tick late (issue 23); excite itself exits 1 on a fault
    assert not any(int(float(r["faults"])) for r in rows), "no fault during the excitation"
    rows = [r for r in rows if r["excite"] == "1"]
    phis = [abs(float(r["phi"])) for r in rows]
    assert len(rows) >= BAL_BOARD_S * 500 and max(phis) > 0.005, "the excitation moved the pendulum"
    # balancing all through (the recorder labels a row with the last heartbeat it has: the first
    # rows of the run may still carry the one from before the arm)
    states = [int(float(r["state"])) for r in rows]
    first = states.index(2, 3) if 2 in states[3:] else len(states)
    assert first < len(states) / 10 and set(states[first:]) == {2}, "balancing all through the excitation"
    robot.hands.do("pendulum", on=False)  # "take the pendulum off"
    try:
        _run_excite(robot, cart)
    finally:
        robot.hands.do("pendulum", on=True)
    rows = list(csv.DictReader(open(robot.tmp / "cart.csv")))
    assert not any(int(float(r["faults"])) for r in rows), "no fault during the cart-only excitation"
    # every tick of the excitation but the first few (the ACK's tick: the PRBS starts on the next)
    assert sum(r["excite"] == "2" and int(r["duty"]) != 0 for r in rows) >= CART_BOARD_S * 500 - 10, \
        "the PRBS drove the cart"


def test_7_excite_and_identify_recover_the_plant(robot: Robot, plant) -> None:
    from sim.params import load_params

    # the pendulum upright (the stand-by person holds it until the board balances)
    robot.hands.do("hold", phi=0.0, until="driving")
    bal = "upright board --port /dev/ttyUSB0 excite --seconds 30 --amplitude 0.5 --out bal.csv"
    cart = "upright board --port /dev/ttyUSB0 excite --cart-only --seconds 15 --amplitude 1 --out cart.csv"
    # board time instead of the README's wall seconds: the same logs on a loaded machine
    EXTRA[bal] = ["--board-seconds", f"{BAL_BOARD_S:g}"]
    # bits of 16 ticks (32 ms, three drive time constants): the cart at full speed at the disarm, most
    # of the time -- the coast-down's start speed is what b is measured from
    EXTRA[cart] = ["--board-seconds", f"{CART_BOARD_S:g}", "--board-coast", f"{COAST_BOARD_S:g}", "--div", "16"]
    # the link watchdog counts board time: 250 ms are 0.6-5 s of wall time here, and on this 2-core
    # machine at a load of 10 the host tool was seen to stall for 1 s between two host heartbeats
    # (four of eight runs latched `watchdog`, excite then exits 1): WATCHDOG_MS for these runs
    wd = robot.params("watchdog_ms")["watchdog_ms"]
    robot.board("params", "set", "watchdog_ms", str(WATCHDOG_MS))
    try:
        _excite_runs(robot, bal, cart)
    finally:
        robot.board("params", "set", "watchdog_ms", str(wd))
    truth = _truth(plant)
    # the first stage alone (issue 24): the cart-only log gives the drive, the friction and the delay
    s1 = subprocess.run(UPRIGHT + ["identify", "cart.csv", "--cart-only", "--params", "robot.toml", "--out",
                                   "stage1.toml"], cwd=robot.tmp, capture_output=True, text=True, timeout=300,
                        env=robot.env)
    if s1.returncode == 2 and "drive model does not fit" in s1.stderr:
        # identify refuses such a log (host/studies/identify_cart.py MAX_RES_COUNTS); seen in two of five
        # cart-only runs on the emulated board here: residual steps of about one encoder count during the
        # run and a cart that stops dead in the coast-down, once with an `enc_jump` fault in the balancing
        # run before -- encoder counts lost between the virtual robot's quadrature edges and the board's
        # PIO counter (host/hil/virtual_robot.py, host/hil/emulated.py PinDrive), not the identification
        pytest.xfail(f"the cart-only log is not the plant's motion: {s1.stderr.strip().splitlines()[-1][-240:]}")
    assert s1.returncode == 0, s1.stdout + s1.stderr
    st1 = load_params(robot.tmp / "stage1.toml")
    IDENT["stage1"] = {"b": st1.b, "kt": st1.kt, "delay": st1.delay}
    cmd = "upright identify bal.csv cart.csv --params robot.toml --out robot_id.toml"
    r = subprocess.run(UPRIGHT + robot.argv(cmd), cwd=robot.tmp, capture_output=True, text=True, timeout=300,
                       env=robot.env)
    assert r.returncode == 0, f"{cmd}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    IDENT["got"] = got = _truth(load_params(robot.tmp / "robot_id.toml"))
    IDENT["out"] = r.stdout
    # the identify bench's goal (host/bench/identify.py): every parameter within 10 %, the delay to the
    # sample, the pot offset to a couple of counts
    for k in ("b", "kt", "ke", "I"):
        assert abs(got[k] / truth[k] - 1) < 0.10, (k, got[k], truth[k], r.stdout)
    assert abs(got["delay"] - truth["delay"]) * plant.rate <= 1 + 1e-9, (got["delay"], r.stdout)
    assert abs(got["pot_offset"] - truth["pot_offset"]) <= 2, r.stdout
    # m*L: from the logs where they resolve it, else (said so) the robot file's -- the cart's back-EMF
    # damping (44 N s/m) leaves the pendulum's reaction a fraction of an encoder count
    ml = [ln for ln in r.stdout.splitlines() if ln.split()[:1] == ["mL"]]
    assert ml and ("(from --params)" in ml[0] or abs(got["mL"] / truth["mL"] - 1) < 0.10), r.stdout
    for k in ("b", "kt"):
        assert abs(IDENT["stage1"][k] / truth[k] - 1) < 0.10, (k, IDENT["stage1"], s1.stdout)
    assert abs(IDENT["stage1"]["delay"] - truth["delay"]) * plant.rate <= 1 + 1e-9, s1.stdout


def test_7_dashboard_step_moves_the_cart(robot: Robot) -> None:
    from host.dashboard.server import split_url
    from test_dashboard_emulated import TOKEN, _Page, _req, _wait

    robot.hands.do("hold", phi=0.0, until="driving")
    p = subprocess.Popen(UPRIGHT + robot.argv("upright dashboard --port /dev/ttyUSB0"), cwd=robot.tmp,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=robot.env,
                         start_new_session=True)
    page = None
    try:
        url = p.stdout.readline().strip()  # type: ignore[union-attr]
        assert url.startswith("http://127.0.0.1:"), p.stderr.read() if p.poll() is not None else url  # type: ignore[union-attr]
        url, TOKEN[""] = split_url(url)  # the page's per-run token: commands carry it
        page = _Page(url)
        _req(url + "api/ping", b"{}", page.id)
        assert _req(url + "api/clear", b"{}", page.id)[0] == 200  # Clear (a fault an earlier step latched)
        code, body = _req(url + "api/arm", b"{}", page.id)
        assert code == 200, body
        _wait(url, lambda s: (s.get("heartbeat") or {}).get("state_name") == "balancing", 120, "balancing")
        x0 = robot.hands.do("state")["x"]
        code, body = _req(url + "api/reference", json.dumps({"x": 0.1}).encode(), page.id)
        assert code == 200, body
        st = robot.hands.do("wait", seconds=2.5)  # the step settles in about 2 s of board time
        assert st["driving"] and abs(st["phi"]) < 0.1, st
        assert abs(st["x"] - x0 - 0.1) < 0.03, (x0, st)  # the cart moved by the step
        code, body = _req(url + "api/disarm", b"{}", page.id)
        assert code == 200, body
    finally:
        if page is not None:
            page.close()
        os.killpg(p.pid, signal.SIGINT)
        try:
            p.wait(timeout=60)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def test_8_hil_on_the_board_agrees_with_the_virtual_board(robot: Robot) -> None:
    cmd = "upright hil --port /dev/ttyUSB0"
    r = subprocess.run(UPRIGHT + robot.argv(cmd), cwd=robot.tmp, capture_output=True, text=True, timeout=600,
                       env=robot.env)
    assert r.returncode == 0, f"{cmd}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    # the answer time follows the emulated board's measured speed (no fixed 2 s of wall time);
    # the run says what it measured, what it will take, and where it is
    assert re.search(r"board clock at 0\.\d\dx the wall's: \d+ s per answer", r.stderr), r.stderr
    assert re.search(r"estimate: .* in all at \d+ ticks/s", r.stderr), r.stderr
    assert "[1/1] short_tilt: 100% (500/500 ticks)" in r.stderr, r.stderr
    v = subprocess.run(UPRIGHT + ["hil", "--virtual", "--scenario", str(robot.tmp / "short_tilt.toml"), "--no-plots",
                                  "--out", "hil_virtual", "--json", "hil_virtual.json"], cwd=robot.tmp,
                       capture_output=True, text=True, timeout=600, env=robot.env)
    assert v.returncode == 0, v.stderr
    [hp] = json.loads((robot.tmp / "hil_port.json").read_text())
    [hv] = json.loads((robot.tmp / "hil_virtual.json").read_text())
    # the same firmware in the same lockstep loop, on the emulated Pico and on the unix port
    assert hp["passed"] and hv["passed"], (r.stdout, v.stdout)
    assert hp["phi_max"] == pytest.approx(hv["phi_max"], abs=2e-3), (hp, hv)
    assert hp["accel_max"] == pytest.approx(hv["accel_max"], rel=0.05), (hp, hv)
    robot.run("upright board --port /dev/ttyUSB0 mode robot")
    st = json.loads(robot.board("status", "--json").stdout)
    assert st["state"] == "disarmed", st


COMMISSION = "upright commission --port /dev/ttyUSB0 --out commission"
RESUME = COMMISSION + " --resume"


def test_9_commission_stage_by_stage(robot: Robot, plant) -> None:
    # the section's first step: the whole commissioning on the virtual robot, one stage per command
    # (--until STAGE, then --resume: what the README says a stopped run does), --fast for the test's
    # time (shorter cart-only run, fewer design candidates); the virtual robot's hands do the person's
    # steps. Wall time: the board runs at 0.05-0.2x real time here, each run counted in its ticks
    from host.operate.commission import STAGES
    from sim.params import load_params

    out = robot.tmp / "commission"
    times = {}
    for i, stage in enumerate(STAGES):
        cmd = COMMISSION if i == 0 else RESUME
        t0 = time.monotonic()
        r = subprocess.run(UPRIGHT + robot.argv(cmd) + ["--fast", "--until", stage], cwd=robot.tmp,
                           capture_output=True, text=True, timeout=1800, env=robot.env)
        times[stage] = time.monotonic() - t0
        assert "Traceback" not in r.stderr, r.stderr[-3000:]
        if stage != "save":
            assert r.returncode == 0, f"{stage}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
            assert f"stopped after {stage} (--until)" in r.stdout, r.stdout[-2000:]
        done = json.loads((out / "commission.json").read_text())["done"]
        assert done == list(STAGES[:i + 1]), (stage, done)
        if stage == "identity":
            assert "x real time (emulated)" in r.stdout, r.stdout  # the board's speed measured
        if stage == "calibrate":
            cal = load_params(out / "robot_cal.toml")
            assert abs(cal.pot_offset - plant.pot_offset) <= 1 and abs(cal.enc_cpr / plant.enc_cpr - 1) < 0.005
        if i > STAGES.index("calibrate"):  # a resumed run first uploads the table in force again
            assert "resumed: uploaded the table in force" in r.stdout, r.stdout[-2000:]
    data = json.loads((out / "commission.json").read_text())["data"]
    print("commission wall s per stage:", {k: round(v) for k, v in times.items()})
    # verified on the robot itself: the 20 cm step from its telemetry (the push needs a pushed cart)
    ver = data["verify"]
    assert "skipped" in ver["push_0p2N_5s"], ver
    step = ver["ref_step_20cm"]
    assert r.returncode == (0 if step["pass"] else 1), r.stdout + r.stderr
    assert step["pass"] and not step["fell"], step
    assert (out / "report.html").exists() and load_params(out / "robot.toml")
    # the board balanced through every run: nothing latched, the board disarmed at the end
    st = json.loads(robot.board("status", "--json").stdout)
    assert st["state"] == "disarmed" and st["faults"] == 0, st


def test_every_command_of_the_section_ran() -> None:
    assert RAN == set(COMMANDS), sorted(set(COMMANDS) - RAN)
