"""Run the firmware's fixed-point code on measurement sequences, under MicroPython or CPython.

Used by the firmware tests and ``host/bench/firmware.py``.  The float reference is
:class:`host.design.discrete.DiscreteController`; the firmware is ``firmware/controller.py``
(and the whole ``firmware/app.py`` with a scripted HAL).  Sequences are passed to the
interpreter once and every tick runs inside one interpreter process, so a test of
thousands of ticks costs one start-up.

The integer inputs of the controller are what ``firmware/sensors.py`` produces:
``yx = encoder counts << QX``, ``yp = (adc - pot_offset) << QP`` and the reference in x LSB.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from host.design.discrete import DiscreteController, simulate_loop
from host.design.export import LAYOUT, FixedDesign, export
from host.boards.mpyrun import run_unix, run_wasm
from sim.params import RobotParams

__all__ = ["Sequence3", "measurements", "controller_inputs", "mp_controller_run", "py_controller_run",
           "fixed_controller", "FAKE_HAL", "layout_of", "ref_lsb"]

# a scripted HAL for MicroPython/CPython runs of the app: the test sets adc/enc and
# reads duty; ticks advance by `inc` us per call (two calls per step)
FAKE_HAL = """
class Hal:
    def __init__(s):
        s.adc = 2048
        s.enc = 0
        s.duty = 0
        s.t = 0
        s.inc = 250
        s.n_set = 0
    def read_angle_raw(s):
        return s.adc
    def read_encoder(s):
        return s.enc
    def set_motor(s, d):
        s.duty = d
        s.n_set += 1
    def ticks_us(s):
        s.t = (s.t + s.inc) & 0x3FFFFFFF
        return s.t
"""


def layout_of(fd: FixedDesign) -> list[tuple[str, int]]:
    """The concrete (name, length) layout of a design (``"D"`` resolved)."""
    return [(n, fd.delay if ln == "D" else int(ln)) for n, ln in LAYOUT]


def ref_lsb(fd: FixedDesign, x_m: float) -> int:
    """A reference in metres as the firmware converts it (um, then RNUM/RSH, clamped)."""
    rmul, rdiv = fd.tables["REF"]
    um = int(round(x_m * 1e6))
    r = (um * rmul + (rdiv >> 1)) // rdiv
    lim = fd.tables["RLIM"][0]
    return max(-lim, min(lim, r))


@dataclass
class Sequence3:
    """Measurements as the float controller saw them and as the firmware gets them."""

    x_meas: np.ndarray  # m
    phi_meas: np.ndarray  # rad
    x_ref: np.ndarray  # m
    yx: list[int]
    yp: list[int]
    r: list[int]
    u_float: np.ndarray  # N, the float controller's saturated output on the same inputs


def controller_inputs(params: RobotParams, fd: FixedDesign, x_meas: Sequence[float], phi_meas: Sequence[float],
                      x_ref: Sequence[float]) -> tuple[list[int], list[int], list[int], np.ndarray, np.ndarray]:
    """Quantise SI measurements to encoder/ADC counts and the firmware's integer inputs.

    Returns ``yx, yp, r`` (ints) and the quantised measurements in SI (what a float
    controller reading the same sensors sees).
    """
    mpc = 2 * math.pi * params.r_wheel / params.enc_cpr
    rpc = params.pot_range / 2**params.adc_bits
    qx, qp = fd.fmt["QX"], fd.fmt["QP"]
    ylx, ylp = fd.tables["YLIM"]
    enc = np.clip(np.rint(np.asarray(x_meas) / mpc).astype(int), -ylx, ylx)
    adc = np.clip(np.rint(np.asarray(phi_meas) / rpc).astype(int), -ylp, ylp)
    yx = [int(v) << qx for v in enc]
    yp = [int(v) << qp for v in adc]
    r = [ref_lsb(fd, float(v)) for v in x_ref]
    return yx, yp, r, enc * mpc, adc * rpc


def measurements(params: RobotParams, fd: FixedDesign, x0: Sequence[float], duration: float,
                 x_ref: float | Callable[[float], float] = 0.0,
                 disturbance: Callable[[float], float] | None = None) -> Sequence3:
    """A scenario of the nonlinear plant closed by the float controller, as sequences.

    The float controller is re-run on the quantised measurements so ``u_float`` is
    exactly its output for the inputs the firmware gets.
    """
    c = fd.ctrl
    sim = simulate_loop(params, c, x0, duration, x_ref=x_ref, quantise=True, disturbance=disturbance)
    yx, yp, r, xq, pq = controller_inputs(params, fd, sim["x_meas"], sim["phi_meas"], sim["x_ref"])
    rq = np.array(r) * fd.lsb["x"]
    z = c.initial_state()
    u = np.empty(len(yx))
    for k in range(len(yx)):
        _, u[k], z = c.tick(z, [xq[k], pq[k], rq[k]])
    return Sequence3(sim["x_meas"], sim["phi_meas"], sim["x_ref"], yx, yp, r, u)


def _ints(vals: Sequence[int]) -> str:
    return " ".join(str(int(v)) for v in vals)


# big literals would sit on the interpreter's value stack (the wasm port's pystack is
# small): sequences travel as one string each and are parsed into arrays
INTS_SRC = """
from array import array
def ints(s):
    a = array('i')
    for w in s.split():
        a.append(int(w))
    return a
"""


def _flat_src(fd: FixedDesign) -> str:
    return INTS_SRC + f"LAYOUT = {tuple(layout_of(fd))!r}\nFLAT = tuple(ints({_ints(fd.flat())!r}))\n"


def mp_controller_run(fd: FixedDesign, yx: Sequence[int], yp: Sequence[int], r: Sequence[int],
                      runner: str = "unix") -> tuple[list[int], list[int]]:
    """Run ``firmware.controller.Controller`` under MicroPython over a sequence.

    Returns the force (u LSB) and speed estimate (xdot LSB) of every tick.
    """
    code = (
        "from array import array\nfrom firmware.controller import Controller\n"
        + _flat_src(fd)
        + f"YX = ints({_ints(yx)!r})\nYP = ints({_ints(yp)!r})\nR = ints({_ints(r)!r})\n"
        + """
c = Controller(LAYOUT, FLAT)
n = len(YX)
U = array('i', [0] * n)
V = array('i', [0] * n)
for k in range(n):
    U[k] = c.step(YX[k], YP[k], R[k])
    V[k] = c.vh
print(' '.join(str(v) for v in U))
print(' '.join(str(v) for v in V))
"""
    )
    out = (run_unix if runner == "unix" else run_wasm)(code).strip().splitlines()
    return [int(v) for v in out[0].split()], [int(v) for v in out[1].split()]


def py_controller_run(fd: FixedDesign, yx: Sequence[int], yp: Sequence[int], r: Sequence[int]) -> tuple[list[int], list[int]]:
    """The same firmware controller under CPython (identical integer semantics)."""
    from firmware.controller import Controller

    c = Controller(layout_of(fd), fd.flat())
    u, v = [], []
    for k in range(len(yx)):
        u.append(c.step(yx[k], yp[k], r[k]))
        v.append(c.vh)
    return u, v


def fixed_controller(params: RobotParams, fd: FixedDesign) -> Callable[[int, float, float, float], float]:
    """A ``simulate_loop`` controller callable running the firmware controller (CPython).

    Measurements are quantised like the sensors; returns the saturated force in N.
    """
    from firmware.controller import Controller

    c = Controller(layout_of(fd), fd.flat())
    mpc = 2 * math.pi * params.r_wheel / params.enc_cpr
    rpc = params.pot_range / 2**params.adc_bits
    qx, qp = fd.fmt["QX"], fd.fmt["QP"]
    ylx, ylp = fd.tables["YLIM"]
    su = fd.lsb["u"]

    def f(k: int, xm: float, pm: float, xr: float) -> float:
        yx = max(-ylx, min(ylx, int(round(xm / mpc)))) << qx
        yp = max(-ylp, min(ylp, int(round(pm / rpc)))) << qp
        return c.step(yx, yp, ref_lsb(fd, xr)) * su

    return f


def default_design() -> FixedDesign:
    """The design of the generated ``firmware/gains.py``."""
    return export()


APP_LOOP = FAKE_HAL + """
import sys
from firmware.app import App
hal = Hal()
app = App(hal, config=CONFIG)
hal.adc = ADC0
hal.enc = ENC0
app.step()
app.cmd_set_reference(REF_UM)
app.cmd_arm()
while True:
    line = sys.stdin.readline()
    if not line:
        break
    w = line.split()
    hal.adc = int(w[0])
    hal.enc = int(w[1])
    if len(w) > 2:
        app.cmd_set_reference(int(w[2]))
    app.step()
    sys.stdout.write('%d %d %d %d\\n' % (hal.duty, app.ctrl.u, app.sup.state, app.sup.faults))
"""


class MicroPythonApp:
    """The whole firmware app in a MicroPython unix-port process, stepped over a pipe.

    Each :meth:`step` sends one sensor reading (ADC counts, 16-bit encoder counter,
    optionally a new reference in um) and returns ``(duty, u_lsb, state, faults)``.
    The app is armed at start (watchdog off) so it balances as soon as the tilt is
    inside the arming window.  Use as a context manager.
    """

    def __init__(self, adc0: int, enc0: int, ref_um: int = 0, config: dict | None = None) -> None:
        import os
        import subprocess

        from host.boards.mpyrun import ROOT, micropython_exe

        cfg = {"watchdog_ms": 0, **(config or {})}
        code = f"CONFIG = {cfg!r}\nADC0 = {adc0}\nENC0 = {enc0}\nREF_UM = {ref_um}\n" + APP_LOOP
        env = dict(os.environ, MICROPYPATH=f"{ROOT}:.frozen")
        self.proc = subprocess.Popen([micropython_exe(), "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, bufsize=1, env=env, cwd=ROOT)

    def step(self, adc: int, enc: int, ref_um: int | None = None) -> tuple[int, int, int, int]:
        """One control tick; returns ``(duty, u_lsb, state, faults)``."""
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(f"{adc} {enc}\n" if ref_um is None else f"{adc} {enc} {ref_um}\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            err = self.proc.stderr.read() if self.proc.stderr else ""
            raise RuntimeError(f"MicroPython app stopped: {err}")
        a, b, c, d = (int(v) for v in line.split())
        return a, b, c, d

    def close(self) -> None:
        """End the interpreter."""
        if self.proc.stdin:
            self.proc.stdin.close()
        self.proc.wait(timeout=10)

    def __enter__(self) -> "MicroPythonApp":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def app_closed_loop(params: RobotParams, x0: Sequence[float], duration: float, *, x_ref: float = 0.0,
                    rate: float | None = None, substeps: int = 2, config: dict | None = None) -> dict[str, np.ndarray]:
    """The nonlinear plant closed around the firmware app running under MicroPython.

    Sensors as ``sim/sensors.py`` (ADC counts, 16-bit encoder, ``delay`` ticks late, no
    noise), the duty through the DC-motor model ``sim/motor.py`` (back EMF included).
    The arming window is widened to 0.15 rad so a run may start from the report's 0.1 rad.
    """
    from sim import motor as smotor
    from sim import sensors as ssens
    from sim.plant import dynamics, rk4_step

    rate = float(params.rate if rate is None else rate)
    Ts = 1.0 / rate
    d = int(round(params.delay * rate))
    n = int(round(duration / Ts))
    phys = params.physical
    x = np.asarray(x0, dtype=float).copy()
    hist = [x.copy()] * (d + 1)

    def f(xx: np.ndarray, uu: float) -> np.ndarray:
        return dynamics(0.0, xx, np.array([uu]), phys)

    def meas(xx: np.ndarray) -> tuple[int, int]:
        return int(ssens.phi_to_adc(xx[2], params)), int(ssens.x_to_encoder(xx[0], params))

    cols = {k: np.zeros(n) for k in ("t", "x", "xdot", "phi", "phidot", "duty", "force", "state")}
    adc0, enc0 = meas(x)
    cfg = {"arm_tilt_mrad": 150, **(config or {})}
    with MicroPythonApp(adc0, enc0, int(round(x_ref * 1e6)), cfg) as fw:
        for k in range(n):
            adc, enc = meas(hist[0])
            duty, _, state, _ = fw.step(adc, enc)
            F = float(smotor.force_from_duty(duty, x[1], params))
            cols["t"][k] = k * Ts
            for j, name in enumerate(("x", "xdot", "phi", "phidot")):
                cols[name][k] = x[j]
            cols["duty"][k], cols["force"][k], cols["state"][k] = duty, F, state
            for _ in range(substeps):
                x = rk4_step(f, x, F, Ts / substeps)
            hist = hist[1:] + [x.copy()]
    return cols
