"""The lockstep emulated HIL reads the motor pins' state at the start of each scenario
(issue 27 follow-up: a uniform-noise run started right after the white-noise run on the same
emulated board showed that run's last duty, -8364 counts, at t = 0 with the board disarmed).
:class:`host.hil.emulated.PinDrive` integrates the duty from the PWM writes and DIR/EN edges of
the runs it reads; the set-up between two scenarios (disarm, clear, gains, arm) ran through
runs it did not read, so the first tick started from the previous scenario's last pin state.
``EmulatedHil.run`` now calls :meth:`PinDrive.sync` with the set-up's last run.  Runs in
milliseconds (no board: StepResults as the harness returns them)."""

from __future__ import annotations

from firmware import board as fwboard
from host.boards.rp2040.board import StepResult
from host.hil.emulated import PinDrive


class _NoBoard:
    def set_adc(self, v: int) -> None:
        pass

    def set_encoder(self, total: int, within_us: float = 0.0) -> None:
        pass


def _result(cycles: int, compare: int, en: int, dir_: int = 1, events: list | None = None,
            edges: list | None = None) -> StepResult:
    return StepResult(cycles=cycles, pwm_compare=compare, pwm_top=6249, pwm_enabled=True, pwm_div=16,
                      duty=compare / 6250, dir=dir_, en=en, uart_tx=b"", uart_tx_cycles=[], usb_tx=b"",
                      edges=edges or [], pwm_events=events or [], uart_baud=1_000_000, halted=False,
                      waiting=False, idle_cycles=0, pc=0, wall_s=0.0)


def _balancing_then_disarmed() -> tuple[PinDrive, StepResult]:
    pins = PinDrive(_NoBoard())
    # the last tick of a scenario: driving hard backwards (compare 1595 of 6250, DIR high, EN high)
    last = _result(1_000_000, 1595, 1, events=[(750_000, 1595, 6249, True, 16)],
                   edges=[(fwboard.EN_PIN, 750_000, 1), (fwboard.DIR_PIN, 750_000, 1)])
    assert pins.duty(last, 750_000, 1_000_000) < -8000  # -8362 counts
    # the set-up of the next scenario (not read through duty): disarmed, compare 0, EN low
    setup = _result(5_000_000, 0, 0, events=[(1_200_000, 0, 6249, True, 16)],
                    edges=[(fwboard.EN_PIN, 1_200_000, 0)])
    return pins, setup


def test_the_first_tick_after_the_set_up_reads_the_pins_as_the_set_up_left_them() -> None:
    pins, setup = _balancing_then_disarmed()
    pins.sync(setup)
    first = _result(5_250_000, 0, 0)  # no writes in the first tick: the board still disarmed
    assert pins.duty(first, 5_000_000, 5_250_000) == 0.0
    assert pins.en_fraction == 0.0


def test_without_the_sync_the_previous_scenarios_duty_leaks_into_tick_zero() -> None:
    # the defect the sync removes (positive control for the test above)
    pins, _setup = _balancing_then_disarmed()
    first = _result(5_250_000, 0, 0)
    assert pins.duty(first, 5_000_000, 5_250_000) < -1000
