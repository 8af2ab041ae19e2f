"""No host message makes a tick late: the request sweep on a balancing emulated Pico.

The bundle's ``main.py`` (HalPico, the paced loop with the heap locked, UART0 at 1 Mbaud)
balances the simulated pendulum through its pins (:class:`host.hil.emulated.EmulatedHil`);
every host-to-board message of the table is sent singly, then in bursts of back-to-back frames
at the line's full rate (:mod:`host.bench.link_sweep`).  Asserted with the firmware's own rule
and figures: no loop iteration over 1.5 periods, ``stats_loop.overruns`` and the status value
``late_ticks`` (the firmware's own clock: a gap over 1.5 periods between step starts, a late
tick, ``App._period``) unchanged by the sweep, balancing
without a fault after every message; the bursts made frames wait (``link_deferred``), each no
longer than the admission rule's FORCE ticks.  Timed with the XIP flash-cache model (the predicted real
Pico).  ``make bench`` (section ``link``) prints the worst gap per message.  One board for the
configuration: about 45-70 s of wall time.  Two configurations: the shipped one, and a robot with
1 mm of gear play and 0.2 N of Coulomb friction with the board parameters ``upright commission``
sets for it (``gear_play``, ``cart_coulomb``: the step's gap model and the compensation's push run
in every tick of the sweep).
"""

from __future__ import annotations

import pytest

from firmware import admit
from host.bench.link_sweep import BURST, sweep
from host.boards.rp2040.board import EmulatedBoard, build_bundle
from host.hil.emulated import EmulatedHil

pytestmark = pytest.mark.rp2040  # slow; skipped without the emulated board (tests/conftest.py)


@pytest.fixture(scope="module", params=["shipped", "gear_play"])
def result(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory):
    # timed with the XIP flash-cache model on (the predicted real Pico, issue 26): command code
    # runs from a cold cache, 300-1530 us a frame (ideal cycles: 60-400 us).  Before the link
    # budgeted in that time, a burst of 12 stats requests made a gap of 3162 us and 8 overruns
    from firmware import msgtable as T
    from fwharness import play_robot

    params, board_params = None, None
    if request.param == "gear_play":
        params, board_params = play_robot()
        assert board_params[T.P_GEAR_PLAY] > 0 and board_params[T.P_CART_COULOMB] > 0, board_params
    bundle = build_bundle(tmp_path_factory.mktemp("bundle"))
    with EmulatedBoard(bundle, main=True, xip_cache=True) as board, EmulatedHil(bundle, board=board) as hil:
        yield sweep(hil, params=params, board_params=board_params)


def test_every_message_singly_and_in_bursts_leaves_the_loop_on_time(result) -> None:
    p = result["period_us"]
    labels = [f.label for f in result["steps"]]
    # every board-bound message of the table is in the sweep
    from host.link import messages as M

    for c in M.MESSAGES.values():
        if c.DIRECTION == "to_board" and c.NAME != "disarm":
            assert any(lab.split("#")[0].split("(")[0] in (c.NAME, f"burst {c.NAME}") for lab in labels) or \
                c.NAME == "arm" and "arm (repeat)" in labels, c.NAME
    # an iteration over 1.5 periods is a late tick for sure.  The probe's gap between iteration
    # starts is not asserted: it finds iterations between busy-wait clusters (>= 3 TIMER reads),
    # and a tick that runs past its period (the link's budget allows up to 1.5 periods less the refill) is followed by
    # the next without a wait, so the probe may join two steps into one gap (seen: a gap of
    # 3022 us after a 2558 us iteration while the firmware's own step-start clock saw no gap
    # over 3000 us).  The firmware's clock is the judge: next test
    late = [(f.label, round(f.iter_us)) for f in result["steps"] if not f.iter_us < 1.5 * p]
    assert not late, f"iterations over 1.5 periods ({1.5 * p:.0f} us): {late}"
    bad = [(f.label, f.state, f.faults) for f in result["steps"] if f.state != 2 or f.faults]
    assert not bad, f"not balancing or a fault after: {bad}"


def test_the_firmware_saw_no_late_tick_and_no_overrun(result) -> None:
    # with the gear-play model on this was 3 late ticks and 3 overruns before the link's budget
    # kept admit.REFILL_US after a frame (the loop's code refilling the flash cache: 466 us
    # traced where the budget kept 250) and the step's wheel-side correction was written out
    # (docs/firmware.md, "Board timing")
    b, a = result["before"], result["after"]
    assert a["stats_loop.overruns"] == b["stats_loop.overruns"], (b, a)
    assert a["late_ticks"] == b["late_ticks"] == 0, (b, a)


def test_bursts_wait_in_the_receive_buffer_and_are_counted(result) -> None:
    b, a = result["before"], result["after"]
    assert a["link_deferred"] > b["link_deferred"], (b, a)
    # a frame goes in a tick that still has the worst frame's time; a tick that ran past its
    # period lets the next one catch up without link work, and a backlog held FORCE ticks in a
    # row gets one frame whatever the time (admit.py): the 2 * BURST frames of the "everything"
    # burst wait FORCE ticks each at most (the sweep drains each step's backlog before the next
    # step).  The figure itself follows the firmware's layout, not its rule: 29 ticks on one
    # build, 43 with one parameter more in msgtable.PARAMS and nothing else changed; 110 in both
    # configurations since the budget keeps admit.REFILL_US after a frame (fewer held frames fit
    # beside a step: more go by forcing)
    assert 2 <= a["link_wait_max"] <= 2 * BURST * admit.FORCE, a


def test_a_set_point_ramp_runs_through_the_requests(result) -> None:
    # the ramp steps (link_sweep.ramps): ref_rate_mm_s on, the set-point moved 5 cm and back, each
    # move followed at once by what `upright board status` asks and every parameter read.  The
    # telemetry's reference passes through values between the ends (the ramp ran in the ticks
    # that handled the requests; a step would jump) and ends at the set-point.  The timing of
    # these steps is in the two tests above (no late iteration, no overrun, no late tick)
    from host.bench.link_sweep import RAMP_MM_S, RAMP_UM

    steps = {f.label: f for f in result["steps"]}
    end = RAMP_UM // 100  # telem_ctrl.ref is in 0.1 mm
    for label, a, b in (("ramp set_reference out, status", 0, end), ("ramp set_reference back, status", end, 0)):
        f = steps[label]
        assert f.state == 2 and f.faults == 0, f
        lo, hi = min(a, b), max(a, b)
        inside = [r for r in f.refs if lo < r < hi]
        # 50 ticks of ramp at 500 mm/s, telemetry every 10th tick: about 5 frames inside
        assert len(inside) >= 2, (label, f.refs)
        assert list(f.refs) == sorted(f.refs, reverse=a > b), (label, f.refs)  # monotonic: no jump back
        assert f.refs[-1] == b, (label, f.refs)
        # no faster than the rate: a telemetry frame every 10 ticks (2 ms each) moves <= 10 * step
        per_frame = RAMP_MM_S * 10 * 2 // 100 + 1  # 0.1 mm
        moves = [abs(y - x) for x, y in zip(f.refs, f.refs[1:])]
        assert max(moves) <= per_frame, (label, f.refs)
