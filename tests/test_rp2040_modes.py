"""One bundle, every use (issue 14 item 1): the bundle ``make firmware`` builds runs the robot at
boot and serves lockstep HIL on the same link after a MODE hil command (no reflash), on UART0 or
on the Pico's USB serial (``firmware/board.py`` ``LINK``).  On the emulated RP2040 (rp2040js,
MicroPython's rp2 port); needs node, rp2040js and build/rp2040/firmware.bin.
"""

from __future__ import annotations

import dataclasses
import re
import shutil
import threading
from pathlib import Path

import numpy as np
import pytest

from firmware import msgtable as T
from host.boards import bundle as B
from host.boards.rp2040.board import ROOT, EmulatedBoard
from host.link import messages as M

pytestmark = pytest.mark.rp2040  # slow; skipped without the emulated board (tests/conftest.py)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # exactly what `make firmware` writes (python -m host.boards.bundle)
    out = tmp_path_factory.mktemp("bundle")
    assert B.main(["--arch", "armv6m", "--out", str(out)]) == 0
    return out


def test_the_bundle_holds_the_hil_main_but_not_the_unix_port(bundle: Path) -> None:
    names = {p.name for p in (bundle / "firmware").iterdir()}
    assert {"main.mpy", "main_hil.mpy", "hal_hil.mpy", "link_serial.mpy", "link_usb.mpy"} <= names
    assert "uart_unix.mpy" not in names


# ------------------------------------------------------------------ UART0: mode hil, a HIL run
def test_mode_hil_over_uart0_then_a_lockstep_hil_run_then_back_to_the_robot(bundle: Path) -> None:
    from host.boards.rp2040.bridge import PtyBridge
    from host.hil.session import HilSession
    from host.operate.board import Board
    from sim.scenario import load_scenario

    stop = threading.Event()
    errors: list[BaseException] = []
    with PtyBridge(bundle) as br:
        def pump() -> None:
            try:
                br.serve(stop.is_set)
            except BaseException as exc:  # noqa: BLE001 - reported by the test
                errors.append(exc)

        th = threading.Thread(target=pump, daemon=True)
        th.start()
        try:
            # robot mode at boot: its heartbeat (the paced loop's) answers
            with Board.open(br.port, timeout=1.0, answer_timeout=20.0) as b:
                b.connect(answer_timeout=20.0)
                st = b.state()
                assert st["state"] == 0, st  # disarmed
                boot = st["boot"]
            # upright hil --port: the session sends MODE hil, then runs lockstep on the same UART
            sc = dataclasses.replace(load_scenario("tilt_0p1"), duration=0.1)
            with HilSession(br.port, mode="lockstep", timeout=8.0) as s:
                assert s._switched
                run = s.run_lockstep(sc)
            # ... and sent MODE robot when it closed: the paced loop runs again
            with Board.open(br.port, timeout=1.0, answer_timeout=20.0) as b:
                b.connect(answer_timeout=20.0)
                st = b.state()
                assert st["state"] == 0 and st["boot"] == boot, st  # no reset on the way
        finally:
            stop.set()
            th.join(timeout=60)
    assert not errors, errors
    n = int(round(0.1 * 500))
    assert run.stats["ticks"] >= n
    # every sensor frame answered by the board's controller: the duty pushes against the tilt
    duty = np.asarray(run.log["duty"])
    assert len(duty) >= n and np.any(duty != 0)
    assert int(run.log["fw_state"][-1]) == 2  # balancing: the firmware's controller closed the loop


# ------------------------------------------------------------------ USB CDC link
USB_REPL_MS = 300


@pytest.fixture(scope="module")
def usb_bundle(tmp_path_factory: pytest.TempPathFactory, bundle: Path) -> Path:
    # the same bundle with the board config's LINK = "usb" (and a short REPL window after reset)
    out = tmp_path_factory.mktemp("usb_bundle")
    shutil.copytree(bundle, out, dirs_exist_ok=True)
    src = (ROOT / "firmware" / "board.py").read_text()
    src, n = re.subn(r'^LINK = "\w+"', 'LINK = "usb"', src, flags=re.M)
    assert n == 1
    src, n = re.subn(r"^USB_REPL_MS = const\(\d+\)", f"USB_REPL_MS = const({USB_REPL_MS})", src, flags=re.M)
    assert n == 1
    tmp = out / "board.py"
    tmp.write_text(src)
    B.compile_module(tmp, out / "firmware" / "board.mpy")
    tmp.unlink()
    return out


def _frames(dec: M.SerialStreamDecoder, data: bytes) -> list[M.Message]:
    return [m for m, _ in dec.feed(data)]


def _exchange(board: EmulatedBoard, dec: M.SerialStreamDecoder, msg: M.Message, seq: int,
              want: str, us: float = 60_000) -> list[M.Message]:
    board.usb_write(M.encode_serial(msg, seq))
    got: list[M.Message] = []
    t = 0.0
    while t < us:
        got += _frames(dec, board.run(2000).usb_tx)
        t += 2000
        if any(m.NAME == want for m in got):
            return got
    raise AssertionError(f"no {want} within {us / 1000:.0f} ms of board time; got {[m.NAME for m in got]}")


def test_usb_link_heartbeat_mode_hil_and_back_to_the_repl(usb_bundle: Path) -> None:
    boot = (usb_bundle / "main.py").read_bytes()
    # main=False: the harness does not wait for UART0 (this board never opens it); main.py is the
    # bundle's own, so the board boots into the firmware as after `make flash`
    from sim.params import load_params

    with EmulatedBoard(usb_bundle, main=False, files={"main.py": boot}) as board:
        board.set_adc(int(round(load_params().pot_offset)))  # the pendulum upright
        # the REPL window, imports, the loop started: its telemetry comes out on USB
        board.run(USB_REPL_MS * 1000)
        board.run_until(lambda r: bool(r.usb_tx), 3_000_000, 10_000)
        dec = M.SerialStreamDecoder()
        got = _exchange(board, dec, M.BY_NAME["request"](msg_id=T.HEARTBEAT), 7, "heartbeat")
        hb = [m for m in got if m.NAME == "heartbeat"]
        assert hb and hb[-1].NAME == "heartbeat" and hb[-1].boot >= 1
        assert board.uart_baud == 0  # UART0 never opened: the link is the USB serial
        # MODE hil over USB, then HIL ticks answered by actuator frames with their ticks
        got = _exchange(board, dec, M.BY_NAME["mode"](mode=T.MODE_HIL), 8, "ack")
        assert [m for m in got if m.NAME == "ack"][-1].msg_id == T.MODE
        # HilMain built (imports, a fresh app): its idle heartbeats come out on USB
        try:
            board.run_until(lambda r: any(m.NAME == "heartbeat" for m in _frames(dec, r.usb_tx)), 3_000_000, 10_000)
        except Exception as exc:
            raise AssertionError(board.tail()) from exc
        for k in range(1, 6):
            got = _exchange(board, dec, M.BY_NAME["hil_sensor"](tick=k, adc=2048, enc=0), 8 + k, "hil_actuator")
            acts = [m for m in got if m.NAME == "hil_actuator"]
            assert acts[-1].tick == k
        # MODE repl: ACK, the link closed, Ctrl-C works again: the raw REPL runs code
        got = _exchange(board, dec, M.BY_NAME["mode"](mode=T.MODE_REPL), 20, "ack")
        assert [m for m in got if m.NAME == "ack"][-1].msg_id == T.MODE
        board.run(50_000)
        assert board.exec("print(1 + 2)").strip() == "3"


def test_usb_link_reset_then_ctrl_c_within_the_window_gives_the_repl(usb_bundle: Path) -> None:
    boot = (usb_bundle / "main.py").read_bytes()
    with EmulatedBoard(usb_bundle, main=False, files={"main.py": boot}) as board:
        # what mpremote does when it connects: Ctrl-C, then Ctrl-A (raw REPL)
        assert board.exec("import firmware.main\nprint('ok')").strip() == "ok"
