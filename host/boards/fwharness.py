"""The firmware's inputs from SI measurements, and a scripted HAL, for runs of the firmware's
fixed-point code under MicroPython or CPython.

Used by ``host/bench/firmware.py``, ``host/studies/identify_sim.py`` and the firmware tests
(whose own harness -- the controller and the whole app stepped in an interpreter -- is
``tests/fwharness.py``).  The float reference is :class:`host.design.discrete.DiscreteController`;
the firmware is ``firmware/controller.py`` (and the whole ``firmware/app.py`` with the scripted
HAL).  Sequences are passed to the interpreter once as text (:data:`INTS_SRC`).

The integer inputs of the controller are what ``firmware/sensors.py`` produces:
``yx = encoder counts << QX``, ``yp = (adc - pot_offset) << QP`` and the reference in x LSB.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from host.design.discrete import simulate_loop
from host.design.export import LAYOUT, FixedDesign
from sim.params import RobotParams

if TYPE_CHECKING:
    import subprocess

__all__ = ["Sequence3", "measurements", "controller_inputs", "FAKE_HAL", "StandInHal", "INTS_SRC", "layout_of",
           "ref_lsb", "app_process", "APP_PIPE", "PipedApp"]

# a scripted HAL for MicroPython/CPython runs of the app: the test sets adc/enc and
# reads duty; ticks advance by `inc` us per call (two calls per step)
FAKE_HAL = """
from firmware.hal_base import Hal as _HalBase
class Hal(_HalBase):
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

_NS: dict = {}
exec(compile(FAKE_HAL, "<FAKE_HAL>", "exec"), _NS)


class StandInHal(_NS["Hal"]):  # type: ignore[misc,valid-type]
    """:data:`FAKE_HAL`'s ``Hal`` under CPython: the one stand-in HAL (the MicroPython scripts
    paste the same source; the firmware tests, ``host/bench/catch.py``).

    Parameters
    ----------
    **values : int
        Start values of its attributes: ``adc``, ``enc``, ``duty``, ``t``, ``inc`` (the
        microseconds each ``ticks_us`` call advances), ``n_set``.

    Raises
    ------
    TypeError
        A name that is not one of its attributes.
    """

    def __init__(self, **values: int) -> None:
        super().__init__()
        for k, v in values.items():
            if not hasattr(self, k):
                raise TypeError(f"StandInHal has no attribute {k!r}")
            setattr(self, k, v)


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


def app_process(code: str) -> "subprocess.Popen[str]":
    """A MicroPython unix-port process running ``code`` (a script stepping the app over its stdin,
    one line a tick, answering on its stdout), with the project on its path."""
    import os
    import subprocess

    from host.boards.mpyrun import ROOT, micropython_exe

    env = dict(os.environ, MICROPYPATH=f"{ROOT}:.frozen")
    return subprocess.Popen([micropython_exe(), "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, bufsize=1, env=env, cwd=ROOT)


# the firmware App on FAKE_HAL, one tick a line over a pipe: a line "adc enc [word ...]" sets the
# sensors, command(app, w) acts on its words (w: the line split; its result r), app.step() runs and
# reply(hal, app, r) goes back as one line.  The script defines CONFIG, ADC0, ENC0 and the hooks:
# start(app) runs after the first step, before the app is armed.
APP_PIPE = """
import sys
from firmware.app import App
hal = Hal()
app = App(hal, config=CONFIG)
hal.adc = ADC0
hal.enc = ENC0
app.step()
start(app)
app.cmd_arm()
while True:
    line = sys.stdin.readline()
    if not line:
        break
    w = line.split()
    hal.adc = int(w[0])
    hal.enc = int(w[1])
    r = command(app, w)
    app.step()
    sys.stdout.write(reply(hal, app, r))
"""


class PipedApp:
    """The whole firmware app (:data:`FAKE_HAL`, the shipped gain table) in a MicroPython unix-port
    process, armed after its first step and stepped one tick a line over a pipe (:data:`APP_PIPE`).

    Parameters
    ----------
    hooks : str
        MicroPython source defining ``start(app)``, ``command(app, w)`` and ``reply(hal, app, r)``
        (the last returns one line, ``\\n`` included), and whatever they use.
    config : dict
        The ``App`` config.
    adc0, enc0 : int
        The sensors of the first step (ADC counts, 16-bit encoder counter).

    Notes
    -----
    Use as a context manager, or :meth:`close` it.
    """

    def __init__(self, hooks: str, config: dict, adc0: int, enc0: int) -> None:
        self.proc = app_process(f"CONFIG = {config!r}\nADC0 = {adc0}\nENC0 = {enc0}\n" + FAKE_HAL + hooks + APP_PIPE)

    def tick(self, adc: int, enc: int, *words: int) -> list[int]:
        """One control tick: the sensors and the hooks' words in, the reply's integers out.

        Raises
        ------
        RuntimeError
            The interpreter stopped (its standard error in the message).
        """
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(" ".join(str(int(v)) for v in (adc, enc, *words)) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            err = self.proc.stderr.read() if self.proc.stderr else ""
            raise RuntimeError(f"MicroPython app stopped: {err}")
        return [int(v) for v in line.split()]

    def close(self) -> None:
        """End the interpreter (its standard input closed)."""
        if self.proc.stdin:
            self.proc.stdin.close()
        self.proc.wait(timeout=10)

    def __enter__(self) -> "PipedApp":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
