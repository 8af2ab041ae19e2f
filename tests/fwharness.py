"""The firmware tests' harness: the fixed-point controller and the whole app run over
measurement sequences under MicroPython (unix or WebAssembly port) or CPython.

Sequences are passed to the interpreter once and every tick runs inside one interpreter
process, so a test of thousands of ticks costs one start-up.  The production pieces it
builds on (the firmware's inputs from SI measurements, the scripted HAL ``FAKE_HAL`` and
its CPython class ``StandInHal``, ``INTS_SRC``) are :mod:`host.boards.fwharness`'s,
re-exported here: tests import this module (``import fwharness as H``).
"""

from __future__ import annotations

import contextlib
import io
import math
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from host.boards.fwharness import (  # noqa: F401 - re-exported for the tests
    FAKE_HAL, INTS_SRC, PipedApp, Sequence3, StandInHal, _ints, app_process, controller_inputs, layout_of,
    measurements, ref_lsb,
)
from host.boards.mpyrun import run_unix, run_wasm
from host.design.export import FixedDesign, export
from sim.params import RobotParams

if TYPE_CHECKING:
    from host.boards.rp2040.board import EmulatedBoard, StepResult

#: the report's four closed-loop cases as :func:`measurements` keywords: the 0.1 rad tilt (report
#: section 3), the 0.2 m reference step (section 3.3), the square wave 0 <-> 0.2 m every 2.2 s (Fig. 3.11)
#: and a constant 0.2 N push for 4 s, then released (Fig. 3.6)
REPORT_SCENARIOS: dict[str, dict] = {
    "tilt_0.1": dict(x0=[0, 0, 0.1, 0], duration=4.0),
    "ref_step_0.2": dict(x0=[0, 0, 0, 0], duration=4.0, x_ref=0.2),
    "ref_square": dict(x0=[0, 0, 0, 0], duration=5.0, x_ref=lambda t: 0.2 if int(t / 2.2) % 2 else 0.0),
    "push_0.2N": dict(x0=[0, 0, 0, 0], duration=5.0, disturbance=lambda t: 0.2 if t < 4.0 else 0.0),
}


# print-and-parse: a MicroPython script records named integer observations with chk() and
# prints them at the end (CHK_END) as "name value" lines, which parse_ints() reads back
CHK_SRC = """
OUT = []
def chk(name, v):
    OUT.append(name + ' ' + str(int(v)))
"""
CHK_END = """
for line in OUT:
    print(line)
"""

# allocation of fn() in bytes on the WebAssembly port (no heap_lock() there: a gc.mem_alloc()
# delta with the collector off): alloc_bytes(fn) returns it, run(name, fn) prints "name bytes"
WASM_ALLOC_RUN = """
import gc
def alloc_bytes(fn):
    gc.collect()
    gc.disable()
    a = gc.mem_alloc()
    fn()
    b = gc.mem_alloc()
    gc.enable()
    return b - a
def run(name, fn):
    print(name, alloc_bytes(fn))
"""


# whether fn() allocated on the unix port (micropython.heap_lock(): an allocation raises
# MemoryError), printed as "name 0" (none) or "name 1"
UNIX_LOCK_RUN = """
import micropython
def run(name, fn):
    micropython.heap_lock()
    try:
        fn()
        ok = 0
    except MemoryError:
        ok = 1
    micropython.heap_unlock()
    print(name, ok)
"""


# an app on FAKE_HAL armed, then stepped n times under micropython.heap_lock() (unix port) with
# the sensors wiggling (the ADC around upright, the encoder across its 16-bit wrap):
# steps_locked(hal, app, n) is 1 when no step allocated, 0 when one did
APP_STEPS_LOCKED = """
import micropython
def steps_locked(hal, app, n):
    hal.adc = 2048
    app.step()
    app.cmd_arm()
    app.step()
    micropython.heap_lock()
    try:
        for k in range(n):
            hal.adc = 2048 + (k % 11) - 5
            hal.enc = (65530 + (k % 9)) & 0xFFFF
            app.step()
        ok = 1
    except MemoryError:
        ok = 0
    micropython.heap_unlock()
    return ok
"""


def host_frames_src(nbytes: int, nframes: int) -> str:
    """A scripted host for a MicroPython script of the board's loop and link, as source.

    It defines ``layout``, ``table``, ``enc`` (the firmware's codec, CRC table and encoder);
    ``add(tick, mid, a=0, b=0, c=0)``, which seals a command as the host does (the integrity check
    of a command that moves the cart), frames it and queues it in ``STREAM`` with the tick it is
    released at (``REL[i]``, ``END[i]``: the i-th frame's release tick and end offset; ``NF``
    frames, ``POS`` bytes); and ``HostEnd``, the base of a stand-in ``machine.UART``: ``write``
    decodes what the board sends, counting the frames by message id (``count``), with ``rd`` and
    ``frame`` (how much of ``STREAM``, how many frames, have gone) and ``give(buf, k)``, which
    hands the next ``k`` bytes to the subclass's ``readinto``; ``report()`` prints the frames the
    board sent by message (``telem_state``, ``telem_ctrl``, ``heartbeat``, ``param_value``,
    ``timing``, ``ack``, ``nack``).

    Parameters
    ----------
    nbytes : int
        The size of ``STREAM``.
    nframes : int
        How many frames ``add`` may queue.

    Returns
    -------
    str
        MicroPython (and CPython) source.
    """
    return f"""
from array import array
from firmware import codec, crc16, framing
from firmware import msgtable as T
from firmware.crc32 import seal
layout = codec.Layout()
table = crc16.make_table()
enc = framing.Encoder(layout, table)
STREAM = bytearray({nbytes})
REL = array('i', [0] * {nframes})  # release tick of each frame
END = array('i', [0] * {nframes})  # end offset of each frame in STREAM
NF = 0
POS = 0
VALS = array('i', [0] * 4)


def add(tick, mid, a=0, b=0, c=0):
    global NF, POS
    VALS[0] = a
    VALS[1] = b
    VALS[2] = c
    seal(layout, mid, VALS, 0, enc.raw, 2)  # the integrity check of a command that moves the cart
    n = enc.encode(mid, NF & 0xFF, VALS, 0)
    STREAM[POS:POS + n] = enc.out[:n]
    POS += n
    REL[NF] = tick
    END[NF] = POS
    NF += 1


class HostEnd:
    def __init__(s):
        s.rd = 0
        s.frame = 0
        s.dec = framing.Decoder(layout, table)
        s.count = array('i', [0] * 32)

    def give(s, buf, k):
        # the next k bytes of STREAM into buf (a read); the frames they complete have gone
        rd = s.rd
        for i in range(k):
            buf[i] = STREAM[rd + i]
        s.rd = rd + k
        while s.frame < NF and END[s.frame] <= s.rd:
            s.frame += 1
        return k

    def write(s, mv):
        dec = s.dec
        for i in range(len(mv)):
            mid = dec.feed(mv[i])
            if mid >= 0:
                s.count[mid] += 1

    def report(s):
        # what the board sent, as "name count" lines (parse_ints)
        for name in ('telem_state', 'telem_ctrl', 'heartbeat', 'param_value', 'timing', 'ack', 'nack'):
            print(name, s.count[getattr(T, name.upper())])
"""


#: the interpreters a firmware snippet runs on, in conftest's ``interp`` fixture order
INTERPRETERS = ("cpython", "unix", "wasm", "rp2040")

# the raw REPL keeps a script's globals and imported modules for the next one: each run on the
# emulated board starts from an empty heap but the interpreter's own (an earlier run's sequences
# and firmware modules are not the next one's heap to carry: with them the board's heap was too
# fragmented for test_rp2040_fast_equal's 6.5 kB array after the fasttick and catch runs)
REPL_CLEAR = ("for _k in [k for k in globals() if not k.startswith('__')]:\n    del globals()[_k]\n"
              "import sys\nfor _k in [k for k in sys.modules if k.startswith('firmware')]:\n    del sys.modules[_k]\n"
              "import gc\ngc.collect()\n")


def run_cpython(code: str, timeout: float = 0.0) -> str:
    """Run a firmware snippet in this CPython process (fresh globals, run as a script); return what it printed.

    Parameters
    ----------
    code : str
        Python source; it can ``from firmware import ...``.
    timeout : float
        Unused (the snippet runs in-process, to its end): the other runners' signature.

    Returns
    -------
    str
        Its standard output.
    """
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        exec(compile(code, "<firmware snippet>", "exec"), {"__name__": "__main__"})
    return buf.getvalue()


class Interp:
    """One interpreter a test body runs a firmware snippet on (conftest's ``interp`` fixture).

    Parameters
    ----------
    name : str
        One of :data:`INTERPRETERS`: ``cpython`` (in-process), ``unix`` (the 64-bit unix port),
        ``wasm`` (the 32-bit WebAssembly port under node), ``rp2040`` (the emulated Pico's raw
        REPL, the ``make firmware`` bundle importable).
    board : EmulatedBoard, optional
        The booted board (``rp2040`` only), shared by every run: its globals are cleared before
        each (:data:`REPL_CLEAR`).

    Attributes
    ----------
    alloc_run : str or None
        The allocation probe's ``run(name, fn)`` source on this interpreter: :data:`UNIX_LOCK_RUN`
        (``name 1`` when ``fn`` allocated) on the unix port, :data:`WASM_ALLOC_RUN` (``name bytes``)
        on the WebAssembly port; ``None`` where there is none here.
    """

    def __init__(self, name: str, board: "EmulatedBoard | None" = None) -> None:
        if name not in INTERPRETERS:
            raise ValueError(f"unknown interpreter {name!r}: one of {INTERPRETERS}")
        if (name == "rp2040") != (board is not None):
            raise ValueError("a board is given for rp2040 and only for it")
        self.name = name
        self.board = board
        self.alloc_run = {"unix": UNIX_LOCK_RUN, "wasm": WASM_ALLOC_RUN}.get(name)

    def __repr__(self) -> str:
        return f"Interp({self.name!r})"

    def run(self, code: str, timeout: float = 120.0) -> str:
        """Run ``code`` on this interpreter and return what it printed.

        Parameters
        ----------
        code : str
            MicroPython-compatible source; it can ``from firmware import ...``.
        timeout : float
            Seconds it may take: wall seconds on the unix and WebAssembly ports, emulated seconds
            on the board; unused under CPython (in-process).

        Returns
        -------
        str
            Its standard output.

        Raises
        ------
        host.boards.mpyrun.MicroPythonError
            The code raised under a MicroPython port (the board: ``BoardExecError``).
        """
        if self.name == "cpython":
            return run_cpython(code)
        if self.name == "unix":
            return run_unix(code, timeout=timeout)
        if self.name == "wasm":
            return run_wasm(code, timeout=timeout)
        assert self.board is not None
        self.board.exec(REPL_CLEAR, timeout=30)
        return self.board.exec(code, timeout=timeout)


def collect_pins(b: "EmulatedBoard", ms: int, until: Callable[[list, list], bool] | None = None
                 ) -> tuple[list, list, list, "StepResult | None"]:
    """Run the emulated board ``ms`` milliseconds, one at a time, gathering what its pins did.

    Parameters
    ----------
    b : EmulatedBoard
        The board (its watched pins and PWM events configured).
    ms : int
        The most milliseconds to run.
    until : callable, optional
        ``until(edges, resets)``, asked after each millisecond: true ends the run early.

    Returns
    -------
    edges, pwm_events, resets : list
        The watched pins' edges, the PWM compare writes and the resets, in order.
    last : StepResult or None
        The last millisecond's result (its pin levels); ``None`` when ``ms`` is 0.
    """
    edges: list = []
    ev: list = []
    resets: list = []
    r = None
    for _ in range(ms):
        r = b.run(1000)
        edges += r.edges
        ev += r.pwm_events
        resets += r.resets
        if until is not None and until(edges, resets):
            break
    return edges, ev, resets, r


def parse_ints(out: str) -> dict[str, int]:
    """The ``name value`` lines of an interpreter's output as a dict (blank lines skipped)."""
    return {k: int(v) for k, v in (line.split() for line in out.splitlines() if line.strip())}


def ints_src(**seqs: Sequence[int]) -> str:
    """Integer sequences as MicroPython source, one ``NAME = ints('...')`` line each (``ints`` is
    :data:`INTS_SRC`'s, so this goes after it)."""
    return "".join(f"{name} = ints({_ints(v)!r})\n" for name, v in seqs.items())


def flat_src(fd: FixedDesign) -> str:
    """:data:`INTS_SRC` and a design's table as MicroPython source: ``LAYOUT`` (concrete) and
    ``FLAT`` (a tuple), what ``Controller(LAYOUT, FLAT)`` takes."""
    return INTS_SRC + f"LAYOUT = {tuple(layout_of(fd))!r}\nFLAT = tuple(ints({_ints(fd.flat())!r}))\n"


def gains_src(name: str, fd: FixedDesign) -> str:
    """A stand-in ``firmware.gains`` module for ``App(hal, gains=...)`` as MicroPython source: a
    class ``name`` with the design's ``VERSION``, ``CRC``, ``LAYOUT`` and ``FLAT`` (after
    :data:`INTS_SRC`)."""
    return (f"class {name}:\n    pass\n{name}.VERSION = {fd.tables['HDR'][0]}\n{name}.CRC = {fd.crc()}\n"
            f"{name}.LAYOUT = {tuple(layout_of(fd))!r}\n{name}.FLAT = tuple(ints({_ints(fd.flat())!r}))\n")


def mp_controller_run(fd: FixedDesign, yx: Sequence[int], yp: Sequence[int], r: Sequence[int],
                      runner: str = "unix") -> tuple[list[int], list[int]]:
    """Run ``firmware.controller.Controller`` under MicroPython over a sequence.

    Returns the force (u LSB) and speed estimate (xdot LSB) of every tick.
    """
    code = (
        "from array import array\nfrom firmware.controller import Controller\n"
        + flat_src(fd)
        + ints_src(YX=yx, YP=yp, R=r)
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


def check_force_against_float(fd: FixedDesign, s: Sequence3, tol: float, name: str) -> None:
    """Assert that the firmware controller running table ``fd`` over scenario ``s``
    (:func:`measurements`) gives the same numbers bit for bit under the unix port and CPython,
    that the scenario exercises the controller (a peak force over 0.1 N), and that its force is
    within ``tol`` N of the float controller's on the same inputs; ``name`` (the scenario's)
    heads the failure message.
    """
    u_mp, v_mp = mp_controller_run(fd, s.yx, s.yp, s.r)
    u_py, v_py = py_controller_run(fd, s.yx, s.yp, s.r)
    assert u_mp == u_py and v_mp == v_py  # MicroPython == CPython, bit for bit
    u = np.array(u_mp) * fd.lsb["u"]
    err = np.max(np.abs(u - s.u_float))
    assert np.max(np.abs(s.u_float)) > 0.1  # the scenario exercises the controller
    assert err <= tol, f"{name}: {err:.4f} N > {tol:.4f} N"


def check_closed_loops_agree(params: RobotParams, ctrl: object, fd: FixedDesign, scenario: dict, tol: float,
                             name: str) -> None:
    """Assert that a report scenario (:data:`REPORT_SCENARIOS`: ``simulate_loop`` keywords) on
    plant ``params``, closed once by the float controller ``ctrl`` and once by its table ``fd`` in
    the firmware's controller (:func:`fixed_controller`, CPython), quantised sensors both, gives
    angles within ``tol`` rad of each other, and that the firmware's loop keeps the report's
    constraint (|phi| < 0.3 rad); ``name`` heads the failure message.
    """
    from host.design.discrete import simulate_loop

    kw = scenario
    a = simulate_loop(params, ctrl, kw["x0"], kw["duration"], x_ref=kw.get("x_ref", 0.0), quantise=True,
                      disturbance=kw.get("disturbance"))
    b = simulate_loop(params, ctrl, kw["x0"], kw["duration"], x_ref=kw.get("x_ref", 0.0), quantise=True,
                      disturbance=kw.get("disturbance"), controller=fixed_controller(params, fd))
    err = np.max(np.abs(a["phi"] - b["phi"]))
    assert err <= tol, f"{name}: {err:.5f} rad"
    assert np.max(np.abs(b["phi"])) < 0.3  # the report's constraint


def check_wasm_equals_cpython(fd: FixedDesign, s: Sequence3, n: int = 1000) -> None:
    """Assert that the firmware controller over the first ``n`` ticks of a scenario gives the same
    forces and speed estimates bit for bit on the 32-bit WebAssembly port as under CPython."""
    u_w, v_w = mp_controller_run(fd, s.yx[:n], s.yp[:n], s.r[:n], runner="wasm")
    u_py, v_py = py_controller_run(fd, s.yx[:n], s.yp[:n], s.r[:n])
    assert u_w == u_py and v_w == v_py


def default_design() -> FixedDesign:
    """The design of the generated ``firmware/gains.py``."""
    return export()


# the hooks of PipedApp's loop for MicroPythonApp: the reference set before arming (REF_UM) and
# by a third word; the reply "duty u_lsb state faults"
_REF_HOOKS = """
def start(app):
    app.cmd_set_reference(REF_UM)
def command(app, w):
    if len(w) > 2:
        app.cmd_set_reference(int(w[2]))
    return 0
def reply(hal, app, r):
    return '%d %d %d %d\\n' % (hal.duty, app.ctrl.u, app.sup.state, app.sup.faults)
"""


class MicroPythonApp(PipedApp):
    """The whole firmware app in a MicroPython unix-port process, stepped over a pipe.

    Each :meth:`step` sends one sensor reading (ADC counts, 16-bit encoder counter,
    optionally a new reference in um) and returns ``(duty, u_lsb, state, faults)``.
    The app is armed at start (watchdog off) so it balances as soon as the tilt is
    inside the arming window.  Use as a context manager.
    """

    def __init__(self, adc0: int, enc0: int, ref_um: int = 0, config: dict | None = None) -> None:
        cfg = {"watchdog_ms": 0, **(config or {})}
        super().__init__(f"REF_UM = {ref_um}\n" + _REF_HOOKS, cfg, adc0, enc0)

    def step(self, adc: int, enc: int, ref_um: int | None = None) -> tuple[int, int, int, int]:
        """One control tick; returns ``(duty, u_lsb, state, faults)``."""
        a, b, c, d = self.tick(adc, enc) if ref_um is None else self.tick(adc, enc, ref_um)
        return a, b, c, d


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


def play_robot() -> tuple[RobotParams, dict[int, int]]:
    """The robot file's robot with 1 mm of gear play and 0.2 N of Coulomb friction, and the board
    parameters ``upright commission`` sets for it (:func:`host.operate.commission.drive_params`:
    ``gear_play``, ``cart_coulomb``) as ``msgtable`` index -> value: what the board tests run the
    step's gap model and the compensation's push with."""
    from host.operate.board import param_info
    from host.operate.commission import drive_params
    from sim.params import load_params

    params = load_params().replace(backlash=0.001, coulomb=0.2)
    return params, {param_info(k)["index"]: v for k, v in drive_params(params).items()}
