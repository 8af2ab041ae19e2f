"""The native and viper builds of the controller step (firmware/fastpath.py) equal the bytecode.

Under the MicroPython unix port: the same scenario sequences and extreme inputs through
Controller.step, fastpath.step_native and fastpath.step_viper give identical outputs,
states and integrators, and a whole app.step() with the viper step allocates nothing.
Under CPython the decorators fall back to plain functions with the same results.
"""

from __future__ import annotations

import pytest

import fwharness as H
from host.boards.fwgen.fastpath import render_fastpath
from host.design.export import export
from host.boards.mpyrun import run_unix
from sim.params import load_params

P = load_params()
FD = export(P, ki=40.0)


def seq_with_extremes() -> tuple[list[int], list[int], list[int]]:
    """The controller's inputs (yx, yp, r): a closed-loop run (a tilt, then a reference step), then
    every sign pattern of the extremes (also test_rp2040_fast_equal.py's)."""
    s = H.measurements(P, FD, [0, 0, 0.1, 0], 3.0, x_ref=lambda t: 0.3 if t > 1.0 else 0.0)
    # append extremes: measurements far past the clamps, reference at its limit
    ylx = FD.tables["YLIM"][0] << FD.fmt["QX"]
    ylp = FD.tables["YLIM"][1] << FD.fmt["QP"]
    rl = FD.tables["RLIM"][0]
    ext = [(ylx, ylp, rl), (-ylx, -ylp, -rl), (ylx, -ylp, rl), (-ylx, ylp, -rl)] * 150
    return s.yx + [e[0] for e in ext], s.yp + [e[1] for e in ext], s.r + [e[2] for e in ext]


@pytest.fixture(scope="module")
def seq():
    return seq_with_extremes()


# the three emitters' controller steps on the sequence (YX, YP, R; GHB, HPX, FC: the gear-play model,
# FC the Coulomb force the predictor is given in the play, Controller.lim[LIM_FC]; with FC, FC_COMP/32 of
# it as the compensation's push in the play, LIM_FCC, and the motor's KDU/KDV for the duty's sign)
STEPS = """
from firmware.controller import Controller, LIM_FC, LIM_FCC, LIM_KDU, LIM_KDV, FC_COMP
from firmware import fastpath
c0 = Controller(LAYOUT, FLAT)
c1 = Controller(LAYOUT, FLAT)
c2 = Controller(LAYOUT, FLAT)
c0.lim[4] = c1.lim[4] = c2.lim[4] = GHB
c0.lim[6] = c1.lim[6] = c2.lim[6] = HPX
c0.lim[LIM_FC] = c1.lim[LIM_FC] = c2.lim[LIM_FC] = FC
c0.lim[LIM_FCC] = c1.lim[LIM_FCC] = c2.lim[LIM_FCC] = (FC * FC_COMP) >> 5
c0.lim[LIM_KDU] = c1.lim[LIM_KDU] = c2.lim[LIM_KDU] = KDU
c0.lim[LIM_KDV] = c1.lim[LIM_KDV] = c2.lim[LIM_KDV] = KDV
n = len(YX)
bad = 0
free = 0
for k in range(n):
    u0 = c0.step(YX[k], YP[k], R[k])
    u1 = fastpath.step_native(c1, YX[k], YP[k], R[k])
    u2 = fastpath.step_viper(c2, YX[k], YP[k], R[k])
    if u0 != u1 or u0 != u2 or c0.vh != c1.vh or c0.vh != c2.vh or c0.integ != c2.integ:
        bad += 1
    if list(c0.lim) != list(c1.lim) or list(c0.lim) != list(c2.lim) or list(c0.b) != list(c1.b) or list(c0.b) != list(c2.b):
        bad += 1
    if c0.lim[5] not in (-GHB, GHB):
        free += 1
    for i in range(4):
        if c0.p[i] != c2.p[i] or c0.p[i] != c1.p[i] or c0.rf[i] != c2.rf[i] or c0.ra[i] != c2.ra[i]:
            bad += 1
print('n', n)
print('bad', bad)
print('last', u0)
print('free', free)
"""

# the shipped table's motor row (Motor.kdu, kdv: the duty's sign the gap model takes)
MOTOR = f"KDU = {FD.tables['MOT'][0]}\nKDV = {FD.tables['MOT'][1]}\n"

# a whole app with each fast emitter (PLAY: the gear play parameter) steps allocation-free
APP = H.FAKE_HAL + H.APP_STEPS_LOCKED + """
from firmware.app import App
from firmware import msgtable as T
for em in ('native', 'viper'):
    hal = Hal()
    app = App(hal, config={'watchdog_ms': 0, 'emitter': em})
    app.param_set(T.P_GEAR_PLAY, PLAY)
    app.param_set(T.P_CART_COULOMB, 50 if FC else 0)
    print('alloc_free_' + em, steps_locked(hal, app, 3000))
    print('state_' + em, app.sup.state)
"""


@pytest.mark.parametrize("ghb, hpx, play, fc", [(0, 0, 0, 0), (4000, 1200, 19, 0), (4000, 1200, 19, 300)],
                         ids=["no gear play", "gear play", "gear play and Coulomb friction"])
def test_native_and_viper_equal_bytecode(seq, ghb: int, hpx: int, play: int, fc: int) -> None:
    # with gear play the gap model (Controller.lim[4], [5]: LIM_GHB, LIM_GAP; the wheel side from lim[6:]) runs too
    yx, yp, r = seq
    code = H.flat_src(FD) + H.ints_src(YX=yx, YP=yp, R=r) + f"GHB = {ghb}\nHPX = {hpx}\nPLAY = {play}\nFC = {fc}\n" + MOTOR + STEPS + APP
    out = dict(line.split() for line in run_unix(code, timeout=120).splitlines() if line.strip())
    assert int(out["n"]) == len(yx) and int(out["bad"]) == 0
    # the sequence crosses the play model's gap (the force reverses) and rests on a flank
    assert (int(out["free"]) > 0) == (ghb > 0) and (ghb == 0 or int(out["free"]) < len(yx) // 2)
    assert out["alloc_free_native"] == "1" and out["alloc_free_viper"] == "1"
    assert out["state_native"] == "2" and out["state_viper"] == "2"


def test_cpython_fallback_equals_bytecode(seq) -> None:
    from firmware import fastpath
    from firmware.controller import Controller

    yx, yp, r = seq
    c0, c2 = Controller(H.layout_of(FD), FD.flat()), Controller(H.layout_of(FD), FD.flat())
    for k in range(len(yx)):
        assert c0.step(yx[k], yp[k], r[k]) == fastpath.step_viper(c2, yx[k], yp[k], r[k])
        assert list(c0.p) == list(c2.p) and c0.integ == c2.integ


def test_fastpath_is_generated_from_the_controller() -> None:
    text = render_fastpath()
    assert "do not edit" in text.splitlines()[0]
    assert "@micropython.viper" in text and "@micropython.native" in text and "self" not in text
