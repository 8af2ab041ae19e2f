"""Every ``upright ...`` command line README.md shows works as shown (issue 11 item 5).

The command lines are read from README.md itself (inline code and code blocks), so a new one
is run without touching this file.  Each runs in a temporary directory with exit status 0
expected.  Long ones get short settings added (:data:`SHORTEN`, the reason next to each);
the ones that cannot run here are in :data:`SKIP`, each with its reason -- a README command
in neither list is run as it stands.  The section "On a real robot" runs in
tests/test_readme_robot.py instead, against one virtual robot (:data:`ROBOT_COMMANDS`: its
commands, the port substituted; none is skipped for want of a board), but for its commands for
a board whose link is on its USB (:data:`USB_LINK`: ``mode repl``), run here against
``upright emulate rp2040 --pty --link usb`` (the emulated Pico's USB CDC port on a pty).
"""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"

# README command (after expansion) -> why it is not run here
SKIP: dict[str, str] = {
    "upright emulate rp2040 --pty": "serves its pty until Ctrl-C; tests/test_rp2040_hil.py::"
                                    "test_emulate_pty_serves_the_host_link_until_sigterm_whatever_stdin_is opens it, "
                                    "tests/test_readme_robot.py runs the README's robot section on it",
    "upright emulate rp2040 --can": "serves its CAN bus until Ctrl-C; tests/test_rp2040_can_hil.py::"
                                    "test_emulate_can_serves_board_status_over_udp_multicast runs upright board on it",
    "upright generate": "rewrites the repository's tracked generated files; the `--check` form is run, "
                        "and tests/test_generated.py renders every file",
}

# README commands for a board whose link is on its USB (the section's "The link on the Pico's USB"):
# run by test_readme_usb_link_commands against `upright emulate rp2040 --pty --link usb`, the
# board's USB CDC port on a pty in place of SHOWN_USB
USB_LINK = ["upright board --port /dev/ttyACM0 mode repl"]
SHOWN_USB = "/dev/ttyACM0"

# command prefix -> arguments added to keep the test short (the reason in the comment)
SHORTEN: dict[str, list[str]] = {
    "upright design": ["--no-search"],  # the LQR weight search alone is ~20 s
    "upright design --robust": ["--candidates", "1"],  # 24 candidates by default: minutes
    "upright dashboard --virtual": ["--seconds", "3", "--http-port", "0"],  # serves until Ctrl-C
    "upright hil --virtual": ["--scenario", "tilt_0p1", "--no-gif"],  # all eight scenarios: a minute
    # tilt_0p1 (5 s) takes ~45 s wall on the emulated board, twice (with and without --json):
    # a 1 s tilt boots the board, balances through its pins and writes every output the same way
    "upright hil --emulate rp2040": ["--scenario", "SHORT_TILT", "--no-gif"],
    "upright demo": ["--scenario", "tilt_0p1", "--no-gif"],  # all eight scenarios with GIFs: minutes
    "upright soak": ["--sim-seconds", "17.6"],  # an hour by default
    "upright sweep robustness": ["--n", "4", "--duration", "0.5", "--no-plots"],
    "upright sweep tune": ["--search", "random", "--designs", "2", "--n", "2", "--duration", "0.5", "--no-plots"],
    "upright sweep tilt": ["--step", "0.2", "--duration", "0.5", "--no-plots"],
    "upright sweep hil": ["--n", "1"],  # 8 runs of 5 s through the firmware by default
}

# placeholders in the README's command lines -> what the test gives
PLACEHOLDERS = {"DIR": "outdir"}

# SHORT_TILT in a SHORTEN list: a 1 s scenario released at 0.05 rad, written into the test's directory
SHORT_TILT = ('name = "short_tilt"\nduration = 1.0\nseed = 1\n[initial]\nphi = 0.05\n'
              '[expect]\nphi_max = "pass"\nsettle = "any"\na_max = "pass"\n')


def _expand(cmd: str) -> list[str]:
    """``[--opt]`` -> without and with; ``a/b/c`` subcommand lists -> one command each."""
    out = [cmd]
    if "[" in cmd:
        out = [re.sub(r"\s*\[[^\]]*\]", "", cmd), re.sub(r"\[([^\]]*)\]", r"\1", cmd)]
    done = []
    for c in out:
        words = c.split()
        for i, w in enumerate(words):
            if "/" in w and not w.startswith(("-", "/", ".")) and re.fullmatch(r"[a-z]+(/[a-z]+)+", w):
                done += [" ".join([*words[:i], alt, *words[i + 1:]]) for alt in w.split("/")]
                break
        else:
            done.append(c)
    return [" ".join(PLACEHOLDERS.get(w, w) for w in c.split()) for c in done]


def readme_commands(text: str | None = None) -> list[str]:
    """Every ``upright ...`` command line of README.md, expanded, in order, without repeats."""
    text = README.read_text() if text is None else text
    found = re.findall(r"`(upright [^`\n]+)`", text)
    for block in re.findall(r"```[a-z]*\n(.*?)```", text, re.S):
        found += [ln.split("#")[0].strip() for ln in block.splitlines() if ln.startswith("upright ")]
    cmds: list[str] = []
    for c in found:
        for e in _expand(c.strip()):
            if e not in cmds:
                cmds.append(e)
    return cmds


COMMANDS = readme_commands()
ROBOT_SECTION = "## On a real robot"


def robot_commands(text: str | None = None) -> list[str]:
    """The commands of README.md's section "On a real robot" (but :data:`SKIP`'s): run by
    tests/test_readme_robot.py against the virtual robot, in the order a user follows them."""
    text = README.read_text() if text is None else text
    start = text.index(ROBOT_SECTION)
    end = text.find("\n## ", start + len(ROBOT_SECTION))
    return [c for c in readme_commands(text[start:end if end >= 0 else None]) if c not in SKIP and c not in USB_LINK]


ROBOT_COMMANDS = robot_commands()
# board commands shown outside that section (the command table): run on the same virtual robot,
# its port given where the README shows the default (tests/test_readme_robot.py)
BOARD_COMMANDS = [c for c in COMMANDS if c == "upright proto dump"]


def test_the_readme_shows_commands() -> None:
    # the extraction works: the table's commands are all there, also soak and the expansions
    for c in ("upright soak", "upright export --out gains.py", "upright proto dump", "upright sweep tilt",
              "upright report seed", "upright report seed --json", "upright design --out outdir"):
        assert c in COMMANDS, COMMANDS
    assert set(SKIP) <= set(COMMANDS), "a skip for a command the README no longer shows"
    assert set(USB_LINK) <= set(COMMANDS), "a USB-link command the README no longer shows"
    # the robot section's commands are run elsewhere, all of them (tests/test_readme_robot.py)
    assert "upright board --port /dev/ttyUSB0 calibrate --out robot.toml" in ROBOT_COMMANDS
    assert "upright hil --port /dev/ttyUSB0" in ROBOT_COMMANDS and len(ROBOT_COMMANDS) >= 14, ROBOT_COMMANDS


def _marks(cmd: str) -> list:
    # the emulated board needs its parts
    return [pytest.mark.rp2040] if "--emulate rp2040" in cmd else []


@pytest.mark.slow  # each an `upright` process: 2-5 s of CPU, the robust search and the emulated board minutes
@pytest.mark.parametrize("cmd", [pytest.param(c, marks=_marks(c)) for c in COMMANDS
                                 if c not in ROBOT_COMMANDS and c not in BOARD_COMMANDS and c not in USB_LINK])
def test_readme_command_works_as_shown(cmd: str, tmp_path: Path) -> None:
    if cmd in SKIP:
        pytest.skip(SKIP[cmd])
    argv = shlex.split(cmd)
    for prefix, extra in SHORTEN.items():
        if cmd == prefix or cmd.startswith(prefix + " "):
            if "--scenario" in argv and "--scenario" in extra:
                # the command names its scenario (a short one): run that one, as shown
                i = extra.index("--scenario")
                extra = extra[:i] + extra[i + 2:]
            argv += extra
    if "SHORT_TILT" in argv:
        (tmp_path / "short_tilt.toml").write_text(SHORT_TILT)
        argv[argv.index("SHORT_TILT")] = str(tmp_path / "short_tilt.toml")
    if "--out" not in argv and argv[1] in ("hil", "demo", "sweep"):
        argv += ["--out", str(tmp_path / "out")]  # as shown it writes under ./out: the temp dir anyway
    r = subprocess.run([sys.executable, "-m", "host.cli.main", *argv[1:]], cwd=tmp_path, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, f"{' '.join(argv)}\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
    assert "Traceback" not in r.stderr
    if "--plant soft_pendulum" in cmd and argv[1] == "hil":  # the README states this run's settling time
        _check_soft_pendulum_claim(r.stdout)
    if argv[1] == "demo":
        _check_demo_table_row(r.stdout, "tilt_0p1")


def _table_row(text: str, name: str) -> list[str]:
    return next(ln for ln in text.splitlines() if ln.startswith(name + " ")).split()


def _check_demo_table_row(stdout: str, name: str) -> None:
    # the README's demo table is the demo's own output: the row of the scenario run here agrees
    # with it (|phi|max 0.005 rad, settle 0.05 s, |a|max 0.1 m/s^2, |F|max 0.1 N; verdicts exactly)
    shown, got = _table_row(README.read_text(), name), _table_row(stdout, name)
    assert len(shown) == len(got), (shown, got)
    for col, tol in ((1, 0.005), (2, 0.05), (4, 0.1), (5, 0.1)):
        assert abs(float(shown[col]) - float(got[col])) <= tol, (col, shown, got)
    assert shown[-3:] == got[-3:], (shown, got)


def _check_soft_pendulum_claim(stdout: str) -> None:
    # the README states the settling time of this run: the figure is the run's own (+-0.05 s)
    claim = re.search(r"settles the 20 cm step, in ([0-9.]+) s", README.read_text())
    assert claim, "README no longer states the soft_pendulum settling time"
    row = next(ln for ln in stdout.splitlines() if ln.startswith("ref_step_20cm"))
    settle = float(row.split()[2])
    assert abs(settle - float(claim.group(1))) <= 0.05, (settle, claim.group(1))


@pytest.mark.slow
def test_readme_scenario_format_loads_and_runs(tmp_path: Path) -> None:
    """The scenario TOML the README documents is a valid scenario, and it runs."""
    from sim.scenario import load_scenario

    text = README.read_text().split("### Scenario files", 1)[1]
    block = re.search(r"```toml\n(.*?)```", text, re.S).group(1)  # type: ignore[union-attr]
    tomllib.loads(block)
    path = tmp_path / "readme.toml"
    path.write_text(block)
    s = load_scenario(path)
    assert s.name == "push_0p2N_5s" and len(s.forces) == 2 and s.reference.kind == "step"
    r = subprocess.run([sys.executable, "-m", "host.cli.main", "simulate", "--scenario", str(path), "--csv",
                        str(tmp_path / "o.csv")], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr


def test_host_tools_default_to_the_boards_uart_rate() -> None:
    from firmware.board import UART_BAUD
    from host.cli.main import build_parser

    p = build_parser(only="hil")
    assert p.parse_args(["hil"]).baudrate == UART_BAUD == 1_000_000
    p = build_parser(only="proto")
    a = p.parse_args(["proto", "dump"])
    assert a.baudrate == UART_BAUD and a.link == "/dev/ttyUSB0"


def test_readme_decode_example_is_its_encode_example() -> None:
    """The README's ``proto decode`` bytes are what its ``proto encode`` line produces (one message)."""
    enc = next(c for c in COMMANDS if c.startswith("upright proto encode "))
    dec = next(c for c in COMMANDS if c.startswith("upright proto decode "))
    r = subprocess.run([sys.executable, "-m", "host.cli.main", *shlex.split(enc)[1:]], capture_output=True,
                       text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[0] == dec.split()[-1], (enc, r.stdout, dec)


@pytest.mark.slow
@pytest.mark.rp2040
def test_readme_usb_link_commands(tmp_path: Path) -> None:
    """The README's USB-link commands (``mode repl``) on the emulated Pico with its host link on USB.

    ``upright emulate rp2040 --pty --link usb`` serves the board's USB CDC port (the Pico's
    micro-USB, /dev/ttyACM0 on a real one) on a pty; the command runs with that pty for
    :data:`SHOWN_USB`, and the README's promise is checked: the port is handed back to
    MicroPython's REPL (Ctrl-C gives its prompt, it runs a line), ready for ``make flash``.
    About 60-90 s of wall time (the boot, the board's 2 s REPL window at 0.1-0.2x real time).
    """
    import os
    import signal
    import time

    import serial

    env = dict(os.environ, TMPDIR=str(tmp_path))
    p = subprocess.Popen([sys.executable, "-m", "host.cli.main", "emulate", "rp2040", "--pty", "--link", "usb"],
                         cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, env=env, start_new_session=True)
    try:
        usb = p.stdout.readline().strip()  # type: ignore[union-attr]
        uart = p.stdout.readline().strip()  # type: ignore[union-attr]
        assert usb.startswith("/dev/pts/") and uart.startswith("/dev/pts/") and usb != uart, (
            p.stderr.read() if p.poll() is not None else (usb, uart))  # type: ignore[union-attr]
        for cmd in USB_LINK:
            assert cmd in COMMANDS, f"README.md no longer shows: {cmd}"
            argv = shlex.split(cmd.replace(SHOWN_USB, usb))[1:]
            # the emulated board's clock runs 3-10x slower than the wall's (as tests/test_readme_robot.py)
            argv[3:3] = ["--timeout", "3", "--answer-timeout", "60"]
            r = subprocess.run([sys.executable, "-m", "host.cli.main", *argv], cwd=tmp_path, capture_output=True,
                               text=True, timeout=300, env=env)
            assert r.returncode == 0 and "Traceback" not in r.stderr, f"{cmd}\n{r.stdout}\n{r.stderr}"
        # the port is MicroPython's REPL again: Ctrl-C gives its prompt, and it runs a line
        with serial.Serial(usb, 115200, timeout=0.5) as s:
            def until(marker: bytes, wall: float = 60.0) -> bytes:
                got, t0 = b"", time.monotonic()
                while marker not in got and time.monotonic() - t0 < wall:
                    got += s.read(256)
                return got

            s.write(b"\r\x03\x03")
            assert b">>> " in until(b">>> "), "no REPL prompt after mode repl"
            s.write(b"print(6 * 7)\r")
            assert b"\r\n42\r\n" in until(b"\r\n42\r\n"), "the REPL did not run the line"
        os.killpg(p.pid, signal.SIGTERM)
        assert p.wait(timeout=60) == 0, p.stderr.read()  # type: ignore[union-attr]
        assert list(tmp_path.iterdir()) == [], ("temporary files left behind", sorted(map(str, tmp_path.rglob("*"))))
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
