"""The link's request sweep on a balancing emulated Pico: no host message makes a tick late.

The board runs the bundle's ``main.py`` (``HalPico``, the paced ``App.run`` with the heap locked,
the UART0 link at 1 Mbaud) with the simulated pendulum on its pins
(:class:`host.hil.emulated.EmulatedHil`: ADC, quadrature edges, PWM/DIR/EN read back).  Once it
balances, every host-to-board message of the table is sent -- one at a time, then in bursts of
back-to-back frames at the line's full rate (one character time apart, as a USB-serial adapter
sends a burst) -- each followed by :data:`SETTLE_TICKS` plant ticks.  For each message the loop
iterations the harness found (its loop probe: ``App.run`` busy-waits on the TIMER between
iterations) give the worst gap between two step starts (a late tick is a gap over 1.5 periods,
``App._period``) and the longest iteration (step + link poll; over one period is an overrun); at
the end the firmware's own figures (``stats_loop.overruns``, ``stats_link`` deferred frames and
the longest wait) and the heartbeats' state and faults.

:func:`sweep` is what ``tests/test_link_budget_rp2040.py`` asserts on and what ``make bench``
(section ``link``) prints: the worst gap per message.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
import zlib
from typing import Any, Callable, Mapping, Sequence

from firmware import admit
from firmware import msgtable as T
from host.boards.rp2040.board import CYCLES_PER_US, FIRMWARE, ROOT
from host.hil.emulated import EmulatedHil, duty_over
from host.link import messages as M
from sim.params import RobotParams, load_params
from sim.plantsim import PlantSim
from sim.scenario import load_scenario

__all__ = ["SETTLE_TICKS", "BURST", "RAMP_UM", "RAMP_MM_S", "singles", "bursts", "ramps", "sweep", "bench"]

SETTLE_TICKS = 30
"""Plant ticks run after each message (or burst) before the next one (60 ms at 500 Hz)."""
DRAIN_BLOCKS = 40
"""At most this many blocks of ``2 (admit.FORCE + 1)`` ticks a step's backlog is given to drain."""
_PERIODIC = ("telem_state", "telem_ctrl", "heartbeat")  # the board's own frames, not replies
BURST = 12
"""Frames in one burst (about 170 bytes: well inside the board's 1024-byte receive buffer)."""
_SCENARIO = "tilt_0p1"
RAMP_UM = 50_000
"""The set-point move of the ramp steps (um): 5 cm."""
RAMP_MM_S = 500
"""``ref_rate_mm_s`` of the ramp steps: 5 cm in 100 ms (50 ticks), the step's requests inside it."""


def _requests() -> list[int]:
    # every message id a REQUEST can ask for (the board answers or refuses each)
    return [c.ID for c in M.MESSAGES.values() if c.DIRECTION == "to_host"]


def singles(table: bytes, token: int = 0) -> list[tuple[str, list[M.Message]]]:
    """Every host-to-board message of the table, each as a one-frame step of the sweep.

    ``table`` is a gain table (bytes) the upload messages carry, ``token`` the board's arming
    token (``gains_begin`` carries it).  ``disarm`` is not here: the sweep sends it last (it
    ends balancing).
    """
    B = M.BY_NAME
    out: list[tuple[str, list[M.Message]]] = []
    for c in M.MESSAGES.values():
        if c.DIRECTION != "to_board" or c.NAME in ("disarm",):
            continue
        out += [(f"{c.NAME}", [m]) for m in _instances(c.NAME, table, token)]
    for mid in _requests():
        out.append((f"request({M.MESSAGES[mid].NAME})", [B["request"](msg_id=mid)]))
    # de-duplicate labels (param_set has several instances)
    seen: dict[str, int] = {}
    res = []
    for label, msgs in out:
        k = seen.get(label, 0)
        seen[label] = k + 1
        res.append((label if k == 0 else f"{label}#{k}", msgs))
    return res


def _instances(name: str, table: bytes, token: int) -> list[M.Message]:
    # representative instances of one command (harmless to a balancing robot, or refused)
    B = M.BY_NAME
    c = B[name]
    if name == "param_set":
        # a harmless one (the value in force) and the ones that would tip the robot (refused)
        return [c(index=T.P_TELEM_DIV, value=10), c(index=T.P_MOTOR_SIGN, value=-1),
                c(index=T.P_POT_OFFSET, value=100), c(index=T.P_ENC_SIGN, value=-1)]
    if name == "param_get":
        return [c(index=i) for i in (0, T.N_PARAMS - 1)]
    if name == "gains_begin":
        return [_fill(c, nbytes=len(table), crc=M.crc16(table), token=token)]
    if name == "gains_chunk":
        return [c(offset=0, data=table[:T.CHUNK_BYTES])]
    if name == "gains_commit":
        return [_fill(c, check=zlib.crc32(table))]
    if name == "excite":
        return [_fill(c, mode=T.EXC_ADD, div=4, amp_mn=100), _fill(c, mode=T.EXC_OFF, div=1, amp_mn=1)]
    if name == "set_reference":
        return [_fill(c, x_um=0)]
    if name == "mode":
        return [c(mode=T.MODE_HIL)]
    if name == "hil_sensor":
        return [c(tick=0, adc=2048, enc=0)]
    if name == "request":
        return []  # one per id, below
    if name == "arm":
        return []  # sent with the board's arming epoch by the sweep itself
    return [_fill(c)]


def _fill(c: type[M.Message], **kw: Any) -> M.Message:
    # the fields given, 0 for the rest of the table's (a check field is the class's own)
    names = [f.name for f in c.FIELDS]
    for n in names:
        if n not in kw and n != "check":
            kw[n] = 0
    return c(**{k: v for k, v in kw.items() if k in names})


def _status() -> list[M.Message]:
    # what `upright board status` asks: the heartbeat, the version, the stats, the timing
    req = M.BY_NAME["request"]
    return [req(msg_id=T.HEARTBEAT), req(msg_id=T.VERSION), req(msg_id=T.STATS_DECODE), req(msg_id=T.TIMING)]


def bursts(table: bytes, token: int = 0) -> list[tuple[str, list[M.Message]]]:
    """Bursts of :data:`BURST` back-to-back frames: the same message again and again (each kind a
    tool sends in a loop), what ``upright board status`` sends, and everything at once."""
    B = M.BY_NAME
    st = B["request"](msg_id=T.STATS_DECODE)
    out = [
        ("burst request(stats)", [st] * BURST),
        ("burst param_get", [B["param_get"](index=i % T.N_PARAMS) for i in range(BURST)]),
        ("burst param_set", [B["param_set"](index=T.P_TELEM_DIV, value=10)] * BURST),
        ("burst param_set refused", [B["param_set"](index=T.P_MOTOR_SIGN, value=-1)] * BURST),
        ("burst request(version)", [B["request"](msg_id=T.VERSION)] * BURST),
        ("burst gains_chunk", [B["gains_chunk"](offset=0, data=table[:T.CHUNK_BYTES])] * BURST),
        ("burst gains_commit", [_fill(B["gains_commit"], check=zlib.crc32(table))] * BURST),
        ("burst set_reference", [_fill(B["set_reference"], x_um=0)] * BURST),
        ("burst status", _status() * 3),
    ]
    every = [m for _, ms in singles(table, token) for m in ms if m.NAME not in ("excite",)]
    out.append(("burst everything", every[:2 * BURST]))
    return out


def ramps() -> list[tuple[str, list[M.Message]]]:
    """The set-point ramp under requests: ``ref_rate_mm_s`` set to :data:`RAMP_MM_S`, the
    set-point moved :data:`RAMP_UM` and back, each move followed at once by what ``upright board
    status`` asks (a heartbeat, the version, the stats, the timing) and every parameter read --
    the ramp branch of the controller's schedule runs in the ticks that handle them."""
    B = M.BY_NAME
    status = _status()
    reads = [B["param_get"](index=i) for i in range(T.N_PARAMS)]
    rate = B["param_set"](index=T.P_REF_RATE, value=RAMP_MM_S)
    return [
        ("ramp set_reference out, status", [rate, _fill(B["set_reference"], x_um=RAMP_UM), *status, *reads]),
        ("ramp set_reference back, status", [_fill(B["set_reference"], x_um=0), *status, *reads]),
    ]


@dataclasses.dataclass
class StepFigures:
    """What one sweep step (one message or burst) did to the loop."""

    label: str
    frames: int
    gap_us: float
    """Worst time between two step starts while it was handled (late: > 1.5 periods)."""
    iter_us: float
    """Longest loop iteration (step + link poll; > one period: an overrun)."""
    state: int
    faults: int
    refs: tuple[int, ...] = ()
    """The reference (``telem_ctrl.ref``, raw LSB of 0.1 mm) of every telemetry frame heard."""


def sweep(hil: EmulatedHil, *, settle_ticks: int = SETTLE_TICKS, steps: Sequence[tuple[str, list[M.Message]]] | None = None,
          progress: Callable[[str], None] | None = None, params: RobotParams | None = None,
          board_params: Mapping[int, int] | None = None) -> dict[str, Any]:
    """Balance the simulated pendulum on an open :class:`EmulatedHil` and send the sweep.

    ``params`` is the simulated robot (default the robot file's), ``board_params`` board
    parameters (``msgtable.P_*`` index -> value) set before arming -- e.g. the gear-play model
    and the Coulomb compensation ``upright commission`` sets for a robot with play
    (``host.operate.commission.drive_params``), whose branch of the step then runs in the sweep.

    Returns ``{"steps": [StepFigures...], "period_us", "before"/"after": firmware stats,
    "disarm": StepFigures}``.

    Raises
    ------
    host.hil.errors.HilError
        The board did not balance or did not answer.
    """
    from host.hil.gains import gain_table

    b = hil._b()
    params = load_params() if params is None else params
    sc = dataclasses.replace(load_scenario(_SCENARIO), duration=3600.0)
    sim = PlantSim(params, sc, seed=1, x0=(0.0, 0.0, 0.02, 0.0))
    if hil.measures_supply:
        b.set_supply_mv(1000.0 * float(sim.params.V_supply))
    period_us = sim.Ts * 1e6
    pc = int(round(period_us * CYCLES_PER_US))
    table, _ = gain_table(None, None)
    adc0, enc0 = sim.read()
    hil._set_pins(adc0, enc0)
    hil._idle(10_000.0)
    B = M.BY_NAME
    hil.request(B["disarm"]())
    hil.request(B["clear_faults"]())
    hil.request(B["param_set"](index=T.P_ARM_TILT, value=500))
    hil.request(B["param_set"](index=T.P_TELEM_DIV, value=10))
    for index, value in (board_params or {}).items():
        got = hil.request(B["param_set"](index=int(index), value=int(value)))
        if got.NAME != "param_value" or got.value != int(value):
            from host.hil.errors import HilError
            raise HilError(f"the board did not take parameter {index} = {value}: {got}")
    arm = _arm_message(hil)
    s = hil._phase(period_us)
    now = b.cycles
    margin = int(round(hil.margin_us * CYCLES_PER_US))
    k = max(0, -(-(now + pc + margin - s) // pc))
    start = s + k * pc - margin
    hil._idle((start - pc - now) / CYCLES_PER_US)
    host = hil.host
    assert host is not None
    host.send(arm)
    hil._run((start - b.cycles) / CYCLES_PER_US, None)
    assert hil.pins is not None
    motor = hil.pins.motor  # the H-bridge pins' state (host.hil.emulated.PinDrive)
    keep = max(1, int(round(hil.keepalive_ms * 1e3 / period_us)))
    tick = [0]
    heard: list[M.Message] = []

    def plant(n: int) -> None:
        for _ in range(n):
            adc, enc = sim.read()
            hil._set_pins(adc, enc)
            if tick[0] % keep == 0:
                host.send(B["host_heartbeat"]())
            c0 = b.cycles
            r, msgs = hil._run(period_us, None)
            heard.extend(m for m, _ in msgs)
            sim.step(int(round(duty_over(motor, r, c0, r.cycles))))
            tick[0] += 1

    plant(400)  # caught and settled (0.8 s)
    if hil._state != 2:
        from host.hil.errors import HilError
        raise HilError(f"the board does not balance before the sweep (state {hil._state}, faults {hil._faults})")
    before = _figures(host, plant, heard)
    hil._iters.clear()
    figures: list[StepFigures] = []

    def one(label: str, msgs: list[M.Message]) -> StepFigures:
        hil._iters.clear()
        heard.clear()
        b.uart_write(b"".join(M.encode_serial(m, host.seq + i) for i, m in enumerate(msgs)))
        host.seq = (host.seq + len(msgs)) & 0xFF
        plant(settle_ticks)
        # what the step left in the board's buffers drains before the next step, so that each
        # step's backlog is its own (the firmware's link_wait_max, the longest backlog, is then
        # one step's): blocks of 2 (FORCE + 1) ticks -- a backlog gets a frame at least once in
        # FORCE + 1 (firmware/admit.py) -- until one hears no reply
        for _ in range(DRAIN_BLOCKS):
            n = sum(1 for m in heard if m.NAME not in _PERIODIC)
            plant(2 * (admit.FORCE + 1))
            if sum(1 for m in heard if m.NAME not in _PERIODIC) == n:
                break
        starts = [s0 for s0, _ in hil._iters]
        gaps = [(c - a) / CYCLES_PER_US for a, c in zip(starts, starts[1:])]
        iters = [(e0 - s0) / CYCLES_PER_US for s0, e0 in hil._iters]
        f = StepFigures(label, len(msgs), max(gaps) if gaps else float("nan"), max(iters) if iters else float("nan"),
                        hil._state, hil._faults, tuple(int(m.ref) for m in heard if m.NAME == "telem_ctrl"))
        if progress is not None:
            progress(f"{label}: gap {f.gap_us:.0f} us, iteration {f.iter_us:.0f} us, state {f.state} faults {f.faults}")
        return f

    if steps is None:
        token = int(_ask(hil, plant, B["request"](msg_id=T.SESSION), "session").token)
        steps = [*singles(table, token), *bursts(table, token), *ramps()]
    for label, msgs in steps:
        figures.append(one(label, msgs))
    figures.append(one("arm (repeat)", [_arm_message(hil, run=plant)]))
    after = _figures(host, plant, heard)
    dis = one("disarm", [B["disarm"]()])
    return {"steps": figures, "disarm": dis, "period_us": period_us, "before": before, "after": after}


def _arm_message(hil: EmulatedHil, run: Callable[[int], None] | None = None) -> M.Message:
    # ARM with the board's arming token (its session / heartbeat), as host.link.clients.Link.arm
    B = M.BY_NAME
    if "session" in B:
        if run is None:
            ses = hil.request(B["request"](msg_id=B["session"].ID))
        else:
            ses = _ask(hil, run, B["request"](msg_id=B["session"].ID), "session")
        return B["arm"](epoch=ses.token)
    if run is None:
        hb = hil.request(B["request"](msg_id=T.HEARTBEAT))
    else:
        hb = _ask(hil, run, B["request"](msg_id=T.HEARTBEAT), "heartbeat")
    return B["arm"](epoch=hb.epoch)


def _ask(hil: EmulatedHil, run: Callable[[int], None], msg: M.Message, want: str) -> M.Message:
    # a request answered while the plant keeps running (the robot balances meanwhile)
    assert hil.host is not None
    got: list[M.Message] = []
    orig = hil.host.feed

    def feed(data: bytes) -> list[tuple[M.Message, int]]:
        out = orig(data)
        got.extend(m for m, _ in out if m.NAME == want)
        return out

    hil.host.feed = feed  # type: ignore[method-assign]
    try:
        hil.host.send(msg)
        for _ in range(50):
            run(1)
            if got:
                return got[-1]
    finally:
        hil.host.feed = orig  # type: ignore[method-assign]
    from host.hil.errors import HilError
    raise HilError(f"no {want} reply while balancing")


def _figures(host: Any, plant: Callable[[int], None], heard: list[M.Message]) -> dict[str, int]:
    # the firmware's own figures, asked for while it balances: STATS_LOOP and the status values
    B = M.BY_NAME
    heard.clear()
    host.send(B["request"](msg_id=T.STATS_DECODE))
    for k, name, *_ in T.STATUS:
        host.send(B["param_get"](index=T.STATUS_BASE + k))
    plant(20)
    out: dict[str, int] = {}
    names = {T.STATUS_BASE + k: name for k, name, *_ in T.STATUS}
    for m in heard:
        if m.NAME == "stats_loop":
            out.update({f"stats_loop.{f.name}": int(getattr(m, f.name)) for f in m.FIELDS})
        elif m.NAME == "param_value" and m.index in names:
            out[names[m.index]] = int(m.value)
    return out


def bench(quick: bool = False) -> dict[str, Any]:
    """``make bench`` section ``link``: the sweep on the emulated Pico, the worst gap per message.

    Returns ``{"rows": [...], "table": str, ...}`` as the other sections do; skipped (a note)
    without node, rp2040js or the image.
    """
    if shutil.which("node") is None or not (ROOT / "node_modules" / "rp2040js").is_dir() or not FIRMWARE.is_file():
        return {"title": "link sweep on the emulated Pico", "rows": [],
                "notes": ["skipped: node, rp2040js or the RP2040 image missing"]}
    t0 = time.perf_counter()
    with EmulatedHil() as hil:
        res = sweep(hil)
    wall = time.perf_counter() - t0
    p = res["period_us"]
    rows = [{"message": f.label, "frames": f.frames, "worst_gap_us": round(f.gap_us, 1),
             "gap_periods": round(f.gap_us / p, 3), "longest_iter_us": round(f.iter_us, 1),
             "late": bool(f.gap_us > 1.5 * p), "state": M.STATES.get(f.state, str(f.state)), "faults": f.faults}
            for f in res["steps"]]
    d = res["disarm"]
    # disarm: the motor goes off, then the heap is sampled between ticks (not timed, no late tick)
    rows.append({"message": "disarm (then a heap sample, motor off)", "frames": 1, "worst_gap_us": round(d.gap_us, 1),
                 "gap_periods": round(d.gap_us / p, 3), "longest_iter_us": round(d.iter_us, 1), "late": "n/a",
                 "state": M.STATES.get(d.state, str(d.state)) + " (last heartbeat)", "faults": d.faults})
    worst = max(rows[:-1], key=lambda r: r["worst_gap_us"])
    notes = [f"balancing the simulated pendulum, period {p:.0f} us: a late tick is a gap over {1.5 * p:.0f} us "
             f"between step starts, an overrun an iteration over {p:.0f} us",
             f"worst gap {worst['worst_gap_us']:.0f} us ({worst['message']}), "
             f"{sum(r['late'] is True for r in rows[:-1])} messages with a late tick",
             f"firmware figures before the sweep {res['before']}, after {res['after']}",
             f"{wall:.0f} s wall"]
    return {"title": "link sweep: every host message to a balancing emulated Pico (worst loop gap per message)",
            "rows": rows, "notes": notes, "before": res["before"], "after": res["after"]}
