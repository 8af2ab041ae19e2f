"""A pause of the loop between ticks (a save's flash writes, a heap walk) while the cart rolls is
not an encoder fault: the counts of the pause go into the position (``Sensors.follow``, called by
``App.run`` after each pause), and the next tick's one-tick jump check sees only its own step.
Found on the virtual robot: calibrate's save while the lifted wheels coasted latched ``enc_jump``
and the user's next ``arm`` was refused."""

from __future__ import annotations

import fwharness as H
from firmware import fasttick as F
from firmware import gains as G
from firmware.sensors import Sensors


def _offsets() -> dict[str, int]:
    off, o = {}, 0
    for name, n in G.LAYOUT:
        off[name] = o
        o += n
    return off


def test_the_counts_of_a_pause_are_followed_without_a_jump() -> None:
    off = _offsets()
    for cls in (Sensors, F.SensorsV):
        for sign in (1, -1):
            s = cls(G.FLAT, off, 1, sign)
            lim = s.encj
            s.update(2048, 1000)
            s.update(2048, 1010)
            assert not s.jump and s.pos == 10 * sign
            s.follow(1010 + 20 * lim)  # 20 ticks' worth of the fastest cart, during a save
            s.update(2048, 1010 + 20 * lim + 3)
            assert not s.jump, cls
            assert s.pos == (10 + 20 * lim + 3) * sign, (cls, s.pos)
            # the same step inside one tick is a jump
            s.update(2048, 1010 + 40 * lim + 3)
            assert s.jump, cls


def test_the_paced_loop_follows_the_encoder_across_a_pause() -> None:
    # the paced loop, disarmed: a host asks for heap statistics (sampled between ticks, a pause),
    # and the cart rolls 20 ticks' worth of counts meanwhile; no fault, the counts in the position
    from firmware.app import App
    from firmware.supervisor import F_ENC_JUMP

    hal = H.StandInHal(inc=300)
    app = App(hal, config={"watchdog_ms": 0, "stall_ms": 0})
    lim = app.sensors.encj
    n = [0]

    class Poll:
        def poll(self) -> None:
            n[0] += 1
            if n[0] == 20:
                app._heap_due = True  # what fill_stats asks for

    sample = app.sample_heap

    def slow_sample() -> None:
        sample()
        if n[0] >= 20:
            hal.enc += 20 * lim  # rolled during the heap walk

    app.sample_heap = slow_sample
    app.set_link(Poll())
    app.run(40)
    assert n[0] == 40
    assert app.sup.faults & F_ENC_JUMP == 0, app.sup.faults
    assert app.sensors.pos == 20 * lim
