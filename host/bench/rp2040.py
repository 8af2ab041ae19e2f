"""Per-tick cost on the emulated RP2040 at 125 MHz, by part and by code emitter (``make bench``).

On the emulated Pico (:class:`host.boards.rp2040.board.EmulatedBoard`: MicroPython's rp2 port,
the project's bundle on its flash) with the real ``HalPico`` and the UART0 link, balancing
(armed, pendulum upright), each part of a tick is timed with the board's own ``time.ticks_us``,
twice: in ideal Cortex-M0+ cycles (``timing`` "ideal": flash reads as fast as RAM, as rp2040js
has them) and with the harness's XIP flash-cache model (``timing`` "predicted": each cache miss
charged what the Pico's QSPI flash takes, calibrated against real Picos by
:mod:`host.bench.rp2040_calibration`: the figure a real board is predicted to show).  One call
at a time with a pause between calls (the UART drains), the heap locked as in the paced loop (no
collection lands in a measurement; large call frames on the C stack), the measuring overhead
subtracted:

sensors      ``HalPico.read_angle_raw`` + ``read_encoder`` + ``Sensors.update`` (viper:
             ``fasttick.sensors_update`` on the slot array, as ``StepV.step`` calls it)
supervisor   ``Supervisor.update`` (viper: ``fasttick.supervisor_update``)
controller   the controller step of the emitter (``Controller.step`` / ``fastpath.step_native`` /
             ``step_viper``: ``App(config={"emitter": ...})``)
motor        ``Motor.duty`` (viper: ``fasttick.motor_duty``) + ``HalPico.set_motor``
link poll    ``SerialLink.poll`` with nothing received and no telemetry due
telemetry    one TELEM_STATE + TELEM_CTRL pair encoded and written to the UART (the paced
             loop's sender: ``pacer.telemetry``, one write for the pair)
heartbeat    one HEARTBEAT frame likewise (``pacer.heartbeat``)
app.step     the whole control step (``App.step``; viper: ``fasttick.StepV.step``), balancing
loop tick    the whole paced-loop iteration (``App.run``: step + link poll, telemetry every
             10th tick as ``main.py`` runs it), found from the outside by the harness's loop
             probe; mean and max over 250 ticks

With the predicted timing the viper figures are also taken under several heap layouts (a
``bytearray`` of 0-48 bytes made on a fresh board before the firmware's imports,
:data:`LAYOUT_PADS`): their min, median and max
by part, and the spread of each -- how far a per-part figure moves with no code changed.

Then the report's 9.3 s square-wave scenario closed on the pins (:mod:`host.hil.emulated`, ``main.py`` as flashed,
predicted timing): its worst loop tick as a percentage of the period, and the emulator's speed
(board seconds per wall second).  Last, the issue's targets on the predicted figures, each with
its figure and ``met`` / ``NOT met``: loop tick mean <= 500 us (the board's emitter,
``firmware/board.py`` EMITTER), the scenario's worst tick <= 70 % of the period, and the free
time per period (period - worst tick) a user's code could have.  The unix-port figures of the same code are :mod:`host.bench.firmware`'s rows
(``make bench`` prints both).
"""

from __future__ import annotations

import shutil
import time
from typing import Any

import numpy as np

from host.boards.rp2040.board import FIRMWARE, ROOT, EmulatedBoard

__all__ = ["bench", "EMITTERS", "SCENARIO"]

EMITTERS = ("bytecode", "native", "viper")
SCENARIO = "square_wave_20cm_2p2s"  # the report's longest scenario (9.3 s), at its own duration
PARTS = ("sensors", "supervisor", "controller", "motor", "link poll", "telemetry", "heartbeat", "app.step")
TICK_TARGET_US = 500.0  # whole tick (a 1 kHz loop with 50 % margin)
WORST_TARGET = 0.70  # worst tick of the scenario / period

SETUP = """
import gc, time, micropython
import firmware.board as B
from firmware.hal_pico import HalPico
from firmware.app import App
from firmware.link_serial import SerialLink
hal = HalPico(B)
uart = hal.uart()
T = time.ticks_us
D = time.ticks_diff


def mk(em, td):
    cfg = B.config()
    cfg['watchdog_ms'] = 10000
    cfg['telem_div'] = td
    cfg['emitter'] = em
    a = App(hal, config=cfg)
    a.set_link(SerialLink(uart, a))
    return a


def per(fn, n):
    # mean us of one call, each call timed alone, 0.4 ms apart (the UART drains), the heap
    # locked as in App.run
    acc = 0
    micropython.heap_lock()
    try:
        for i in range(n):
            t0 = T()
            fn()
            acc += D(T(), t0)
            time.sleep_us(400)
    finally:
        micropython.heap_unlock()
    return acc / n


def parts(em, n):
    a = mk(em, 0)
    a.sup.arm()
    for i in range(3):
        a.step()
    s = a.sensors
    sup = a.sup
    c = a.ctrl
    m = a.motor
    cs = a._cstep
    L = a.link
    e = per(lambda: None, n)
    r = {}
    # the arguments read once (the viper classes' attributes are properties on their slot
    # arrays: cold-path readers, not what the step does), as globals: a lambda closing over
    # more than a few variables allocates its call's arguments
    global cn, ps, rl, jp, dl, yx, yp, ref, u, vh, F, SS, SU, MO
    cn, ps, rl, jp, dl, yx, yp, ref, u, vh = s.counts, s.pos, s.rail, s.jump, s.delta, s.yx, s.yp, a.ref, c.u, c.vh
    if em == 'viper':
        # what StepV.step calls: the functions on the slot arrays
        import firmware.fasttick as F
        SS, SU, MO = s._S, sup._S, m._S
        r['sensors'] = per(lambda: F.sensors_update(SS, hal.read_angle_raw(), hal.read_encoder()), n) - e
        r['supervisor'] = per(lambda: F.supervisor_update(SU, cn, ps, rl, jp, dl, 0, 0, 1), n) - e
        r['motor'] = per(lambda: hal.set_motor(F.motor_duty(MO, u, vh)), n) - e
    else:
        r['sensors'] = per(lambda: s.update(hal.read_angle_raw(), hal.read_encoder()), n) - e
        r['supervisor'] = per(lambda: sup.update(cn, ps, rl, jp, dl, 0, 0), n) - e
        r['motor'] = per(lambda: hal.set_motor(m.duty(u, vh)), n) - e
    r['controller'] = per(lambda: cs(c, yx, yp, ref), n) - e
    r['link poll'] = per(L.poll, n) - e
    r['telemetry'] = per(lambda: L.pacer.telemetry(1), n) - e
    r['heartbeat'] = per(lambda: L.pacer.heartbeat(1), n) - e
    r['app.step'] = per(a.step, n) - e
    print(r, a.sup.state)
    hal.set_motor(0)
"""


def _parts(board: EmulatedBoard, em: str, n: int = 40) -> tuple[dict[str, float], int]:
    out = board.exec(f"parts({em!r}, {n})", timeout=10.0).strip()
    d, state = out.rsplit(" ", 1)
    import ast

    return {k: float(v) for k, v in ast.literal_eval(d).items()}, int(state)


LAYOUT_PADS = (0, 4, 8, 12, 16, 24, 32, 48)
"""Bytes of a ``bytearray`` made (and kept) on a fresh board before the firmware's imports in
:func:`_layouts`: each puts the native code and bytecode the bundle's ``.mpy`` files load into
the heap, and the App's objects, at other addresses."""


def _layouts(em: str = "viper", pads: tuple[int, ...] = LAYOUT_PADS, n: int = 40,
             xip_cache: bool = True) -> dict[str, list[float]]:
    """The per-part figures of :func:`_parts` under several heap layouts, one fresh board each:
    part -> one figure per pad of :data:`LAYOUT_PADS` (the same code and inputs; only where the
    heap puts things differs).  A figure that moves between layouts by more than a change under
    study moves is no evidence of that change (docs/firmware.md, "Board timing")."""
    from sim.params import load_params

    out: dict[str, list[float]] = {}
    for pad in pads:
        with EmulatedBoard(main=False, xip_cache=xip_cache) as b:
            b.set_adc(int(round(load_params().pot_offset)))
            b.exec(f"PAD = bytearray({int(pad)})", timeout=2.0)
            b.exec(SETUP, timeout=5.0)
            p, _ = _parts(b, em, n)
        for k, v in p.items():
            out.setdefault(k, []).append(v)
    return out


def _loop(board: EmulatedBoard, em: str, ticks: int = 250) -> np.ndarray:
    board.exec(f"a = mk({em!r}, 10)\na.sup.arm()", timeout=2.0)
    board.loop_probe(gap_us=50.0)
    board.loop_iters.clear()
    board.exec(f"a.run(n={ticks})", timeout=ticks * 0.004 + 1.0)
    board.loop_probe(False)
    it = np.array([(e - s) / 125.0 for s, e in board.loop_iters])
    return it[2:] if it.size > 4 else it  # the first iterations include the exec's start


def _targets(rows: list[dict[str, Any]], st: dict[str, Any]) -> list[dict[str, Any]]:
    """The issue's two tick targets, each with its measured figure and whether it is met."""
    from firmware import board as fw_board

    em = str(getattr(fw_board, "EMITTER", "bytecode"))
    out: list[dict[str, Any]] = []
    row = next((r for r in rows if r.get("emitter") == em and r.get("timing") == "predicted"), None)
    mean = float(row["loop tick us mean"]) if row is not None else float("nan")
    out.append({"target": f"loop tick mean <= {TICK_TARGET_US:.0f} us ({em}, the board's emitter, predicted)",
                "value": f"{mean:.0f} us", "met": bool(mean <= TICK_TARGET_US)})
    worst = st["tick_us_max"] / st["period_us"]
    out.append({"target": f"worst tick of the scenario <= {100 * WORST_TARGET:.0f} % of the {st['period_us']:.0f} us period",
                "value": f"{100 * worst:.1f} % ({st['tick_us_max']:.0f} us)", "met": bool(worst <= WORST_TARGET)})
    # the default rate: the fastest whose period holds this worst tick with the margin, among
    # the rates that make the design's sensor delay a whole number of ticks
    rate = round(1e6 / st["period_us"])
    held = _fastest_rate(st["tick_us_max"])
    out.append({"target": "default loop rate = the fastest held with that margin (sensor delay a whole number of ticks)",
                "value": f"{rate} Hz default, fastest held {held} Hz", "met": bool(held == rate)})
    return out


def _fastest_rate(worst_us: float) -> int:
    """The fastest loop rate (Hz) whose period holds ``worst_us`` within WORST_TARGET and whose
    period divides the design's sensor delay (``sim/robot.toml`` sensors.delay); 0 if none."""
    import tomllib

    from host.boards.rp2040.board import ROOT as root

    delay_us = round(tomllib.loads((root / "sim" / "robot.toml").read_text())["sensors"]["delay"] * 1e6)
    for rate in range(2000, 0, -1):
        per = 1e6 / rate
        if per != int(per) or delay_us % int(per):
            continue
        if worst_us <= WORST_TARGET * per:
            return rate
    return 0


def bench() -> dict[str, Any]:
    """The emulated RP2040's per-tick figures (see the module docstring)."""
    notes: list[str] = []
    if shutil.which("node") is None or not (ROOT / "node_modules" / "rp2040js").is_dir() or not FIRMWARE.is_file():
        return {"title": "emulated RP2040: per-tick cost", "rows": [],
                "notes": ["skipped: node, rp2040js or build/rp2040/firmware.bin missing (make setup)"]}
    from sim.params import load_params

    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    per_em: dict[tuple[str, str], dict[str, float]] = {}
    parts_speed: dict[str, float] = {}
    for timing in ("ideal", "predicted"):
        with EmulatedBoard(main=False, xip_cache=timing == "predicted") as b:
            b.set_adc(int(round(load_params().pot_offset)))
            b.exec(SETUP, timeout=5.0)
            c0, w0 = b.cycles, time.perf_counter()
            for em in EMITTERS:
                try:
                    p, state = _parts(b, em)
                except Exception as exc:  # noqa: BLE001 - an emitter the port cannot run is a note, not a crash
                    notes.append(f"{em} ({timing}): {str(exc).splitlines()[0]}")
                    continue
                it = _loop(b, em)
                per_em[(em, timing)] = p
                row: dict[str, Any] = {"emitter": em, "timing": timing}
                row.update({f"{k} us": round(v, 1) for k, v in p.items()})
                row["loop tick us mean"] = round(float(it.mean()), 1) if it.size else float("nan")
                row["loop tick us max"] = round(float(it.max()), 1) if it.size else float("nan")
                row["state"] = "balancing" if state == 2 else f"state {state}"
                rows.append(row)
            parts_speed[timing] = (b.cycles - c0) / 125e6 / (time.perf_counter() - w0)
    # the board's emitter under several heap layouts: how far a per-part figure moves
    # with nothing changed but where the heap puts things
    try:
        lay = _layouts("viper")
    except Exception as exc:  # noqa: BLE001 - a note, not a crash
        notes.append(f"heap layouts: {str(exc).splitlines()[0]}")
        lay = {}
    for stat, fn in (("min", np.min), ("median", np.median), ("max", np.max)):
        if lay:
            row = {"emitter": f"viper, {len(LAYOUT_PADS)} heap layouts: {stat}", "timing": "predicted"}
            row.update({f"{k} us": round(float(fn(v)), 1) for k, v in lay.items()})
            rows.append(row)
    if lay:
        notes.append("heap layouts (viper, predicted; a fresh board each, a bytearray of "
                     + "/".join(map(str, LAYOUT_PADS)) + " bytes made before the imports): spread (max - min) / median by part: " + ", ".join(
                         f"{k} {100 * (max(v) - min(v)) / max(float(np.median(v)), 1e-9):.1f} %"
                         for k, v in lay.items()))
    notes.append("emulated time at 125 MHz; ideal = M0+ cycles with flash as fast as RAM (rp2040js), predicted = with "
                 "the XIP flash-cache model (harness.mjs; calibration: the rp2040_calibration section, docs/firmware.md "
                 "'Board timing'); loop tick = App.run iteration (step + link poll, telemetry every 10th tick), "
                 "mean/max of 250")
    for em in EMITTERS:
        i, pr = per_em.get((em, "ideal")), per_em.get((em, "predicted"))
        if i and pr:
            notes.append(f"{em}: predicted / ideal app.step {pr['app.step'] / max(i['app.step'], 1e-9):.2f}x, "
                         f"controller {pr['controller'] / max(i['controller'], 1e-9):.2f}x, "
                         f"link poll {pr['link poll'] / max(i['link poll'], 1e-9):.2f}x")
    if ("bytecode", "predicted") in per_em and ("viper", "predicted") in per_em:
        bc, vp = per_em[("bytecode", "predicted")], per_em[("viper", "predicted")]
        notes.append(f"viper vs bytecode (predicted): controller {bc['controller'] / max(vp['controller'], 1e-9):.1f}x "
                     f"faster, app.step {bc['app.step'] / max(vp['app.step'], 1e-9):.2f}x")
    # a 10 s scenario closed on the pins: worst tick as % of the period, emulator speed
    from host.hil.emulated import EmulatedHil
    from sim.scenario import load_scenario

    sc = load_scenario(SCENARIO)
    with EmulatedBoard(main=True, xip_cache=True) as brd, EmulatedHil(board=brd) as hil:
        run = hil.run(sc)
    st = run.stats
    s = run.summary()
    rows.append({
        "emitter": f"main.py ({SCENARIO}, {sc.duration:g} s)", "timing": "predicted",
        "loop tick us mean": round(st["tick_us_mean"], 1), "loop tick us max": round(st["tick_us_max"], 1),
        "worst tick % of period": round(100 * st["tick_us_max"] / st["period_us"], 1),
        "free us per period": round(st["period_us"] - st["tick_us_max"], 1),
        "overruns": st["overruns"], "emulator board s/wall s": round(st["emu_speed"], 3),
        "state": "as expected" if s.as_expected else "NOT as expected: " + ", ".join(
            f"{c.name} {c.status}" for c in s.checks if not c.as_expected),
    })
    notes.append(f"emulator speed: {st['emu_speed']:.3f} board s per wall s closing the plant on the pins "
                 f"({st['board_s']:.1f} board s in {st['wall_s']:.0f} s, predicted timing), timing the parts: "
                 + ", ".join(f"{k} {v:.3f}" for k, v in parts_speed.items()))
    notes.append(f"free time per period on a predicted real Pico at {1e6 / st['period_us']:.0f} Hz: mean "
                 f"{st['period_us'] - st['tick_us_mean']:.0f} us, worst tick leaves {st['period_us'] - st['tick_us_max']:.0f} us")
    targets = _targets(rows, st)
    for t in targets:
        notes.append(f"target {t['target']}: {t['value']} -> {'met' if t['met'] else 'NOT met'}")
    return {"title": "emulated RP2040 (125 MHz): per-tick cost by part and emitter", "rows": rows, "notes": notes,
            "targets": targets,
            "scenario": {"name": SCENARIO, "duration_s": sc.duration, "as_expected": bool(s.as_expected), **{k: v for k, v in st.items() if k != "nacks"}},
            "total_wall_s": time.perf_counter() - t0}
