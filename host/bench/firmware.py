"""Firmware step time and allocation, side by side in one MicroPython run (``make bench``).

Variants, all fed the same measurement sequence (the report's 0.1 rad tilt scenario, then
a 0.3 m reference step) on the MicroPython unix port:

* ``float matrix``: the straightforward float implementation, ``u = Cc z + Dc v``,
  ``z' = Ac z + Bc v + Bu u`` with the DiscreteController's matrices in lists;
* ``float structured``: the same structured algorithm as the firmware, in floats;
* ``fixed bytecode``: ``firmware.controller.Controller.step`` (what the board runs by default);
* ``fixed native`` / ``fixed viper``: ``firmware/fastpath.py`` (generated from the same code);
* ``app.step`` rows: a whole loop iteration (sensors, supervisor, controller, motor
  mapping, timing statistics) with the bytecode and the viper controller step.

µs/step from ``time.ticks_us`` over ``N`` steps (best of ``REPEATS``), bytes/step from a
``gc.mem_alloc()`` delta with the collector disabled.  A CPython row runs the same
bytecode-variant source (the decorators' plain-Python fallback) for reference.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from host.boards import fwharness as H
from host.design.export import export
from host.boards.mpyrun import run_unix
from sim.params import load_params

__all__ = ["bench", "N", "REPEATS"]

N = 4000
N_ALLOC = 500  # steps measured for allocation (with the collector off: keep the float rows in the heap)
REPEATS = 3

_FLOAT_SRC = """
class FloatMatrix:
    # u = Cc z + Dc v; z' = Ac z + Bc v + Bu u_sat (lists of floats)
    def __init__(s, Ac, Bc, Bu, Cc, Dc, umax):
        s.Ac = Ac
        s.Bc = Bc
        s.Bu = Bu
        s.Cc = Cc
        s.Dc = Dc
        s.umax = umax
        s.n = len(Ac)
        s.z = [0.0] * s.n
        s.zn = [0.0] * s.n
    def step(s, y0, y1, r):
        z = s.z
        Cc = s.Cc
        Dc = s.Dc
        u = Dc[0] * y0 + Dc[1] * y1 + Dc[2] * r
        for j in range(s.n):
            u += Cc[j] * z[j]
        if u > s.umax:
            u = s.umax
        elif u < -s.umax:
            u = -s.umax
        zn = s.zn
        for i in range(s.n):
            row = s.Ac[i]
            bc = s.Bc[i]
            acc = bc[0] * y0 + bc[1] * y1 + bc[2] * r + s.Bu[i] * u
            for j in range(s.n):
                acc += row[j] * z[j]
            zn[i] = acc
        s.z = zn
        s.zn = z
        return u

class FloatStructured:
    # the firmware's algorithm in floats: filter, predictor feedback, delta update
    def __init__(s, M, Kf, kb, kr, Kv, Kvb, Adm, Bd, umax):
        s.M = M
        s.Kf = Kf
        s.kb = kb
        s.kr = kr
        s.Kv = Kv
        s.Kvb = Kvb
        s.Adm = Adm
        s.Bd = Bd
        s.umax = umax
        s.d = len(kb)
        s.p = [0.0] * 4
        s.xf = [0.0] * 4
        s.b = [0.0] * s.d
        s.vh = 0.0
    def step(s, y0, y1, r):
        p = s.p
        xf = s.xf
        M = s.M
        ex = y0 - p[0]
        ep = y1 - p[2]
        for i in range(4):
            xf[i] = p[i] + M[i][0] * ex + M[i][1] * ep
        u = s.kr * r
        v = 0.0
        for i in range(4):
            u -= s.Kf[i] * xf[i]
            v += s.Kv[i] * xf[i]
        b = s.b
        for i in range(s.d):
            u -= s.kb[i] * b[i]
            v += s.Kvb[i] * b[i]
        if u > s.umax:
            u = s.umax
        elif u < -s.umax:
            u = -s.umax
        s.vh = v
        b0 = b[0]
        for i in range(s.d - 1):
            b[i] = b[i + 1]
        b[s.d - 1] = u
        for i in range(4):
            row = s.Adm[i]
            p[i] = xf[i] + row[0] * xf[0] + row[1] * xf[1] + row[2] * xf[2] + row[3] * xf[3] + s.Bd[i] * b0
        return u
"""

_RUN_SRC = """
import gc
import time
from firmware.controller import Controller
from firmware import fastpath
from firmware.app import App

def timed(fn, n):
    best = 1 << 29
    for rep in range(REPEATS):
        fn.reset()
        t0 = time.ticks_us()
        fn.run(n)
        dt = time.ticks_diff(time.ticks_us(), t0)
        if dt < best:
            best = dt
    fn.reset()
    gc.collect()
    gc.disable()
    a = gc.mem_alloc()
    fn.run(NA)
    b = gc.mem_alloc()
    gc.enable()
    return best, b - a

class RunFloat:
    def __init__(s, mk):
        s.mk = mk
        s.reset()
    def reset(s):
        s.c = s.mk()
        s.step = s.c.step
    def run(s, n):
        step = s.step
        for k in range(n):
            step(XF[k], PF[k], RF[k])

class RunFixed:
    def __init__(s, fn):
        s.fn = fn
        s.reset()
    def reset(s):
        s.c = Controller(LAYOUT, FLAT)
    def run(s, n):
        c = s.c
        fn = s.fn
        for k in range(n):
            fn(c, YX[k], YP[k], R[k])

class RunApp:
    def __init__(s, em):
        s.em = em
        s.reset()
    def reset(s):
        s.hal = Hal()
        s.app = App(s.hal, config={'watchdog_ms': 0, 'emitter': s.em, 'tilt_limit_mrad': 1500, 'stall_ms': 0})
        s.hal.adc = 2048
        s.app.step()
        s.app.cmd_arm()
        s.app.step()
    def run(s, n):
        hal = s.hal
        step = s.app._step  # the app's cached bound method: no allocation here
        for k in range(n):
            hal.adc = ADC[k]
            hal.enc = ENC[k]
            step()

rows = (
    ('float matrix', RunFloat(lambda: FloatMatrix(AC, BC, BU, CC, DC, UMAX))),
    ('float structured', RunFloat(lambda: FloatStructured(MM, KF, KB, KR, KV, KVB, ADM, BD, UMAX))),
    ('fixed bytecode', RunFixed(Controller.step)),
    ('fixed native', RunFixed(fastpath.step_native)),
    ('fixed viper', RunFixed(fastpath.step_viper)),
    ('app.step bytecode', RunApp('bytecode')),
    ('app.step viper', RunApp('viper')),
)
for name, fn in rows:
    us, by = timed(fn, N)
    print(name.replace(' ', '_'), us, by)
"""


def _lst(a: Any) -> str:
    return repr([float(v) for v in np.ravel(a)])


def _mat(a: np.ndarray) -> str:
    return repr([[float(v) for v in row] for row in np.atleast_2d(a)])


def _script(fd, seq, adc: list[int], enc: list[int]) -> str:
    c = fd.ctrl
    s = fd.lsb
    d = c.delay_steps
    Phi = np.linalg.matrix_power(c.Ad, d)
    kvb = [float((np.linalg.matrix_power(c.Ad, d - 1 - i) @ c.Bd)[1, 0]) for i in range(d)]
    xf = [float(v * s["x"]) for v in seq.yx]
    pf = [float(v * s["phi"]) for v in seq.yp]
    rf = [float(v * s["x"]) for v in seq.r]
    consts = (
        f"N = {N}\nNA = {N_ALLOC}\nREPEATS = {REPEATS}\nUMAX = {c.u_max!r}\n"
        f"AC = {_mat(c.Ac)}\nBC = {_mat(c.Bc)}\nBU = {_lst(c.Bu)}\nCC = {_lst(c.Cc)}\nDC = {_lst(c.Dc)}\n"
        f"MM = {_mat(c.M)}\nKF = {_lst(c.Kf)}\nKB = {_lst(c.kb)}\nKR = {c.kr!r}\n"
        f"KV = {_lst(Phi[1])}\nKVB = {kvb!r}\nADM = {_mat(c.Ad - np.eye(4))}\nBD = {_lst(c.Bd)}\n"
        f"LAYOUT = {tuple(H.layout_of(fd))!r}\nFLAT = tuple(ints({' '.join(map(str, fd.flat()))!r}))\n"
        f"YX = ints({H._ints(seq.yx)!r})\nYP = ints({H._ints(seq.yp)!r})\nR = ints({H._ints(seq.r)!r})\n"
        f"ADC = ints({H._ints(adc)!r})\nENC = ints({H._ints(enc)!r})\n"
        "XF = [float(v) for v in " + repr(" ".join(repr(v) for v in xf)) + ".split()]\n"
        "PF = [float(v) for v in " + repr(" ".join(repr(v) for v in pf)) + ".split()]\n"
        "RF = [float(v) for v in " + repr(" ".join(repr(v) for v in rf)) + ".split()]\n"
    )
    return H.INTS_SRC + H.FAKE_HAL + _FLOAT_SRC + consts + _RUN_SRC


def _cpython_row(fd, seq) -> dict[str, Any]:
    from firmware.controller import Controller

    c = Controller(H.layout_of(fd), fd.flat())
    t0 = time.perf_counter()
    for k in range(N):
        c.step(seq.yx[k], seq.yp[k], seq.r[k])
    return {"variant": "fixed bytecode (CPython fallback)", "us_per_step": (time.perf_counter() - t0) / N * 1e6,
            "bytes_per_step": "-", "vs_float_matrix": "-"}


def bench() -> dict[str, Any]:
    """Step time and bytes/step of every variant (the BENCHES entry ``firmware``)."""
    p = load_params()
    fd = export(p)
    seq = H.measurements(p, fd, [0, 0, 0.1, 0], (N + 10) * fd.ctrl.Ts, x_ref=lambda t: 0.3 if t > 4.0 else 0.0)
    # raw sensor readings for the app rows (counts as the sensors produce them)
    adc = [p.pot_offset + (v >> fd.fmt["QP"]) for v in seq.yp]
    enc = [(v >> fd.fmt["QX"]) & 0xFFFF for v in seq.yx]
    out = run_unix(_script(fd, seq, adc, enc), timeout=600, heapsize="32m")
    res: dict[str, tuple[float, float]] = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 3:
            res[parts[0].replace("_", " ")] = (int(parts[1]) / N, int(parts[2]) / N_ALLOC)
    ref = res["float matrix"][0]
    rows = [
        {"variant": name, "us_per_step": us, "bytes_per_step": by, "vs_float_matrix": f"{ref / us:.1f}x"}
        for name, (us, by) in res.items()
    ]
    rows.append(_cpython_row(fd, seq))
    fixed = res["fixed bytecode"][0]
    notes = [
        f"MicroPython unix port (64-bit), {N} steps of the same scenario per variant, best of {REPEATS}",
        f"fixed bytecode is {ref / fixed:.1f}x faster than float matrix "
        f"and {res['float structured'][0] / fixed:.1f}x faster than float structured (goal >= 5x)",
        f"float variants allocate {res['float matrix'][1]:.0f} / {res['float structured'][1]:.0f} bytes per step "
        "(boxed floats); every fixed-point row should read 0",
        "µs/step include the loop that feeds the sequence (the same for every row)",
    ]
    return {"title": "firmware control step: float vs fixed point (bytecode, native, viper)", "rows": rows, "notes": notes}


if __name__ == "__main__":  # pragma: no cover
    import json

    print(json.dumps(bench(), indent=2, default=str))
