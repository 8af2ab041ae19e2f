"""The firmware on the emulated RP2040 (host.boards.rp2040): boot, REPL, and the real HalPico
driving the pins the harness observes.  Needs node, rp2040js and build/rp2040/firmware.bin."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from host.boards.rp2040.board import BoardError, BoardExecError, EmulatedBoard, build_bundle

pytestmark = pytest.mark.rp2040  # slow; skipped without the emulated board (tests/conftest.py)

HAL = "import firmware.board as B\nfrom firmware.hal_pico import HalPico\nhal = HalPico(B)\n"
PWM_TOP = 125_000_000 // 20_000 - 1  # 20 kHz at 125 MHz, divider 1


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_bundle(tmp_path_factory.mktemp("bundle"))


@pytest.fixture(scope="module")
def board(bundle: Path):
    with EmulatedBoard(bundle, main=False) as b:
        b.exec(HAL)
        yield b


def test_boots_to_repl_and_runs_code(board: EmulatedBoard) -> None:
    assert board.exec("print(1+2)") == "3\r\n"
    assert board.boot_cycles < 125_000 * 100  # USB enumerated within 100 ms of board time


def test_exec_reports_the_boards_traceback(board: EmulatedBoard) -> None:
    with pytest.raises(BoardExecError, match="ZeroDivisionError"):
        board.exec("1/0")
    assert board.exec("print('still alive')") == "still alive\r\n"


@pytest.mark.parametrize("value", [0, 1, 1234, 2048, 4095])
def test_adc_reads_back_what_the_harness_set(board: EmulatedBoard, value: int) -> None:
    board.set_adc(value, channel=0)
    assert int(board.exec("print(hal.read_angle_raw())")) == value


@pytest.mark.parametrize("duty,direction", [(16384, 0), (-8192, 1), (32767, 0), (-40000, 1), (0, 0)])
def test_set_motor_drives_pwm_dir_enable(board: EmulatedBoard, duty: int, direction: int) -> None:
    board.exec(f"hal.set_enable(1)\nhal.set_motor({duty})")  # enable: the supervisor's, while balancing
    r = board.run(200)  # > one 50 us PWM period: the double-buffered compare is in force
    mag = min(abs(duty), 32767)
    assert r.pwm_enabled and r.pwm_top == PWM_TOP
    assert r.dir == direction and r.en == 1
    assert r.duty == pytest.approx(mag * 2 / 65535, abs=1.5 / (PWM_TOP + 1))
    assert r.uart_baud in (0, 1_000_000) or r.uart_baud > 0


def test_pwm_and_pin_history_has_cycle_times(board: EmulatedBoard) -> None:
    board.exec("hal.set_motor(1000)")
    board.run(200)
    # change the motor 5 ms into the next run, from a timer callback on the board
    board.exec(
        "from machine import Timer\n"
        "t = Timer(mode=Timer.ONE_SHOT, period=5, callback=lambda t: hal.set_motor(-2000))"
    )
    start = board.cycles
    r = board.run(10_000)
    assert r.dir == 1 and r.en == 1
    dir_edges = [(c, v) for p, c, v in r.edges if p == 17]
    assert [v for _, v in dir_edges] == [1]
    assert 4_000 < (dir_edges[0][0] - start) / 125 < 6_000  # at the timer's 5 ms (us of board time)
    assert r.pwm_compare == pytest.approx(4000 * (PWM_TOP + 1) / 65535, abs=1)
    assert any(e[1] == r.pwm_compare and e[3] for e in r.pwm_events), r.pwm_events
    assert all(start <= e[0] <= r.cycles for e in r.pwm_events)


def test_bad_firmware_raises_board_error_quoting_the_traceback(bundle: Path, tmp_path: Path) -> None:
    bad = b"from firmware import board\nraise RuntimeError('boom at import')\n"
    t0 = time.monotonic()
    with pytest.raises(BoardError, match="boom at import") as info:
        with EmulatedBoard(bundle, files={"main.py": bad}) as b:
            b.run(100_000)
    assert "Traceback" in str(info.value)
    assert time.monotonic() - t0 < 60


def test_encoder_counts_quadrature_edges_both_ways(bundle: Path) -> None:
    # Separate board: with a HalPico.read_encoder() that drains the FIFO forever (the PIO pushes
    # on every pass) exec times out and the board is left busy.
    with EmulatedBoard(bundle, main=False) as b:
        b.exec(HAL)
        b.set_encoder(200)
        b.run(2000)
        assert int(b.exec("print(hal.read_encoder())", timeout=0.5)) == 200
        b.set_encoder(-300)
        b.run(5000)
        assert int(b.exec("print(hal.read_encoder())", timeout=0.5)) == (-300) & 0xFFFF
        b.set_encoder(-290)
        b.run(1000)
        assert int(b.exec("print(hal.read_encoder())", timeout=0.5)) == (-290) & 0xFFFF


def test_firmware_main_streams_on_uart_at_1_mbaud(bundle: Path) -> None:
    with EmulatedBoard(bundle) as b:
        assert b.uart_baud == 1_000_000
        data = b.wait_uart(50, timeout_us=200_000)
        assert len(data) >= 50


def test_the_host_uart_interrupts_at_half_its_receive_fifo(board: EmulatedBoard) -> None:
    # MicroPython's default (RXIFLSEL 0: 4 bytes) interrupted the loop every 40 us of a burst at
    # 1 Mbaud; HalPico.uart sets 1/2 (16 bytes) and leaves the transmit level as it was
    board.exec("import machine\nu = machine.UART(0, 1000000)")  # MicroPython's own setting
    default = int(board.exec("print(machine.mem32[0x40034034])"))
    board.exec("u = hal.uart()")
    ifls = int(board.exec("print(machine.mem32[0x40034034])"))
    assert (default >> 3) & 7 == 0 and (ifls >> 3) & 7 == 2 and ifls & 7 == default & 7, (default, ifls)
    assert board.exec("print(u.any())").strip() == "0"


def test_code_that_never_finishes_gives_board_error_in_bounded_time(bundle: Path) -> None:
    with EmulatedBoard(bundle, main=False) as b:
        t0 = time.monotonic()
        with pytest.raises(BoardError, match="did not finish"):
            b.exec("while True:\n    pass", timeout=0.05)
        assert time.monotonic() - t0 < 60
