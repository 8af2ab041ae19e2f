"""Guided commissioning: the robot's sensor calibration measured on the board itself.

:func:`run_calibration` walks a user through four steps (answers through an ``ask``
callback: a terminal, scripted answers in tests, a dashboard):

1. the pendulum held upright and still -> ``pot_offset`` (mean ADC counts) and the noise;
2. tilted by a known angle BACKWARD (away from the cart's forward, +x, direction: the model's
   positive tilt, ``theta = pi + phi`` of the report -- a cart accelerating forward tips the
   pendulum back, ``sim/plant.py``) -> the ADC sign and scale (``pot_range``, the
   potentiometer's electrical travel in rad);
3. the cart rolled forward by a known distance -> the encoder sign and counts per metre
   (``enc_cpr`` with the robot's wheel radius);
4. wheels lifted, the board armed at a low ``max_duty``, the pendulum tilted forward by
   hand: the wheels must drive the cart towards the tilt -> the motor sign (measured on
   the encoder, or asked when the wheels cannot be seen to move).

The result is a robot TOML in ``sim/params.py``'s format (the input robot file with the
``[sensors]`` values replaced, comments kept) for ``upright design --params`` /
``upright board gains upload --params``, and the board's own parameters (``pot_offset``,
``adc_sign``, ``enc_sign``, ``motor_sign`` where its table has them), saved on the board
when it has a save command -- calibrating never means editing code or reflashing.

The steps that need a person can be done by a robot's own hands instead: ``robot`` is an object
with ``do(action, idle=None, **kw)`` -- :class:`host.hil.hands.Hands`, the virtual
robot of ``upright emulate rp2040`` (``upright board calibrate --robot auto`` finds it from the
port; a real robot has none, and the prompts go to the person).  Each step's prompt is printed
all the same, followed by what the robot did.
"""

from __future__ import annotations

import math
import re
import statistics
import time
from pathlib import Path
from typing import Any, Callable

from host.operate.board import Board, BoardError, NotSupported, param_table

MOTOR_TILT_RAD = 0.05
"""Step 4 with a robot's hands: the forward tilt (rad) held while the wheels turn."""

WHEELS_STILL_S = 30.0
"""Board seconds to wait for the lifted wheels to stop after the motor step, before the save."""

__all__ = ["CalibrationError", "sample", "robot_toml", "run_calibration", "robot_hands", "ROBOT_HELP"]

ROBOT_HELP = ("who does the steps that need a person: auto (default) -- the virtual robot of `upright emulate "
              "rp2040` behind this port does them through its hands (a Unix socket named after the port, "
              "host/hil/hands.py), a real robot has none and you are prompted; person -- always prompt; "
              "or the path of a virtual robot's socket")

Ask = Callable[[str, "Callable[[], None] | None"], str]


class CalibrationError(BoardError):
    """A step's measurement makes no sense (nothing moved, a reading railed)."""


def robot_hands(choice: str, port_key: str) -> Any:
    """The hands of ``--robot``: ``"person"`` -> ``None``; ``"auto"`` -> the virtual robot behind
    ``port_key`` (the port, or ``can:INTERFACE:CHANNEL``) if one listens, else ``None``; a path ->
    that socket's robot.

    Raises
    ------
    BoardError
        A socket path given, but no robot answers there.
    """
    from host.hil.hands import Hands, HandsError, find_hands

    if choice == "person":
        return None
    if choice == "auto":
        return find_hands(port_key)
    try:
        return Hands(choice)
    except HandsError as exc:
        raise BoardError(f"--robot: {exc}") from None


def sample(board: Board, seconds: float = 1.0, keepalive: bool = False) -> dict[str, Any]:
    """Raw sensor readings over ``seconds``: ADC mean/std, encoder first/last (unwrapped)."""
    adc: list[int] = []
    enc: list[int] = []
    t_end = time.monotonic() + seconds
    pos = 0
    last = None
    while True:
        if keepalive:
            board.keepalive()
        r = board.raw_sensors()
        adc.append(int(r["adc"]))
        e = int(r["enc"]) & 0xFFFF
        if last is not None:
            d = (e - last) & 0xFFFF
            pos += d - 0x10000 if d >= 0x8000 else d
        last = e
        enc.append(pos)
        if time.monotonic() >= t_end and len(adc) >= 5:
            break
        time.sleep(0.01)
    return {"adc_mean": statistics.fmean(adc), "adc_std": statistics.pstdev(adc), "n": len(adc),
            "enc_first": enc[0], "enc_last": enc[-1], "enc_raw_last": last}


def _enc_delta(a: int, b: int) -> int:
    d = (b - a) & 0xFFFF
    return d - 0x10000 if d >= 0x8000 else d


def robot_toml(base: str, values: dict[str, float], note: str = "") -> str:
    """``base`` robot TOML text with ``[sensors]`` keys replaced by ``values`` (comments kept)."""
    lines = base.splitlines()
    out = []
    section = ""
    done = set()
    for line in lines:
        m = re.match(r"\s*\[([^\]]+)\]", line)
        if m:
            if section == "sensors":
                out.extend(f"{k} = {_fmt(v)}" for k, v in values.items() if k not in done)
                done.update(values)
            section = m.group(1).strip()
        km = re.match(r"(\s*)(\w+)(\s*=\s*)([^#]*?)(\s*(#.*)?)$", line)
        if section == "sensors" and km and km.group(2) in values:
            k = km.group(2)
            line = f"{km.group(1)}{k}{km.group(3)}{_fmt(values[k])}{km.group(5) or ''}"
            done.add(k)
        out.append(line)
    if section == "sensors":
        out.extend(f"{k} = {_fmt(v)}" for k, v in values.items() if k not in done)
        done.update(values)
    if len(done) < len(values):
        out += ["", "[sensors]"] + [f"{k} = {_fmt(v)}" for k, v in values.items() if k not in done]
    head = f"# {note}\n" if note else ""
    return head + "\n".join(out) + "\n"


def _fmt(v: float) -> str:
    return str(int(v)) if float(v).is_integer() else f"{v:.8g}"


def run_calibration(board: Board, ask: Ask, say: Callable[[str], None], *, robot_in: str | Path | None = None,
                    robot_out: str | Path = "robot.toml", tilt_deg: float = 10.0, move_m: float = 0.1,
                    sample_s: float = 1.0, test_duty: int = 6000, motor_check: bool = True,
                    save: bool = True, robot: Any = None) -> dict[str, Any]:
    """The guided calibration (module docstring); returns what was measured and written.

    ``robot``: hands that do the person's steps (module docstring); ``None``: ``ask`` the person.

    Raises
    ------
    NotSupported
        The firmware cannot report its raw sensors.
    CalibrationError
        A step saw no change (nothing moved) or a railed reading.
    """
    from sim.params import DEFAULT_PATH, load_params

    src = Path(robot_in) if robot_in else Path(DEFAULT_PATH)
    p = load_params(src)
    full = 2 ** int(p.adc_bits)
    st = board.state(fresh=True)["state_name"]
    if st in ("armed", "balancing"):
        board.disarm()
    res: dict[str, Any] = {"robot_in": str(src), "robot_out": str(robot_out)}

    def step(prompt: str, action: str | None = None, idle: Callable[[], None] | None = None,
             **kw: Any) -> dict[str, Any]:
        # the person (ask) or the robot's hands do what the prompt says
        if robot is None:
            ask(prompt, idle)
            return {}
        say(prompt.replace(", then press Enter", "").replace("Press Enter to arm", "arming") + " -- the robot does it")
        return robot.do(action, idle=idle, **kw) if action else {}

    # 1. upright
    step("Step 1/4: hold the pendulum exactly upright and still (wheels lifted or the cart held), "
         "then press Enter", "hold", phi=0.0, cart="still")
    up = sample(board, sample_s)
    if up["adc_mean"] <= 0 or up["adc_mean"] >= full - 1:
        raise CalibrationError(f"angle ADC reads {up['adc_mean']:.0f} (a rail): potentiometer open, shorted "
                               "or unpowered -- check its wiring (docs/firmware.md)")
    res["pot_offset"] = int(round(up["adc_mean"]))
    res["adc_noise"] = up["adc_std"]
    say(f"  upright: ADC {up['adc_mean']:.1f} counts (noise {up['adc_std']:.2f} counts rms, {up['n']} samples)")

    # 2. tilt
    step(f"Step 2/4: tilt the pendulum {tilt_deg:g} degrees BACKWARD (away from the cart's forward direction) "
         "and hold it, then press Enter", "hold", phi=math.radians(tilt_deg), cart="still")
    tl = sample(board, sample_s)
    d = tl["adc_mean"] - up["adc_mean"]
    if abs(d) < max(5.0, 6 * (up["adc_std"] + tl["adc_std"])):
        raise CalibrationError(f"the angle reading did not change when tilted ({d:+.1f} counts): is the "
                               "potentiometer turning with the pendulum?")
    res["adc_sign"] = 1 if d > 0 else -1
    counts_per_rad = abs(d) / math.radians(tilt_deg)
    res["pot_range"] = full / counts_per_rad
    say(f"  tilted {tilt_deg:g} deg: {d:+.1f} counts -> ADC sign {res['adc_sign']:+d}, "
        f"{counts_per_rad:.1f} counts/rad, pot_range {res['pot_range']:.4f} rad")

    # 3. move
    step("Step 3/4: back upright; put the cart at a mark, then press Enter", "hold", phi=0.0, cart="still")
    a = sample(board, min(sample_s, 0.3))
    step(f"Step 3/4: roll the cart FORWARD by exactly {move_m * 100:g} cm, then press Enter", "move", dx=move_m)
    b = sample(board, min(sample_s, 0.3))
    de = _enc_delta(a["enc_raw_last"], b["enc_raw_last"])
    if abs(de) < 10:
        raise CalibrationError(f"the encoder moved {de} counts when the cart rolled {move_m * 100:g} cm: "
                               "is it wired (A/B on the board's encoder pins) and powered?")
    res["enc_sign"] = 1 if de > 0 else -1
    res["counts_per_m"] = abs(de) / move_m
    res["enc_cpr"] = int(round(res["counts_per_m"] * 2 * math.pi * p.r_wheel))
    say(f"  rolled {move_m * 100:g} cm: {de:+d} counts -> encoder sign {res['enc_sign']:+d}, "
        f"{res['counts_per_m']:.0f} counts/m, enc_cpr {res['enc_cpr']} (wheel radius {p.r_wheel} m)")

    # the board's parameters first: the motor check runs the controller on these signs
    table = param_table()
    on_board = {k: res[k] for k in ("pot_offset", "adc_sign", "enc_sign") if k in table}
    for k, v in on_board.items():
        board.param_set(k, v)

    # 4. motor sign
    res["motor_sign"] = board.param_get("motor_sign") if "motor_sign" in table else 1
    if motor_check:
        res["motor_sign"] = _motor_sign(board, ask, say, res, test_duty, step, robot is not None)
        if "motor_sign" in table:
            board.param_set("motor_sign", res["motor_sign"])
            on_board["motor_sign"] = res["motor_sign"]
    res["board_params"] = on_board
    res["saved"] = None
    if motor_check:
        if robot is not None:
            # the person stops the lifted wheels by hand (the virtual robot's lifted wheels carry the
            # cart's mass and coast for many board seconds)
            step("Step 4/4: stop the wheels by hand", "hold", phi=0.0, cart="still")
        _wait_wheels_still(board, say, timeout=board.wall(WHEELS_STILL_S))
    if save:
        try:
            res["saved"] = board.save()
            say(f"  saved on the board ({res['saved']}): {on_board}")
        except NotSupported as exc:
            res["saved"] = None
            say(f"  not saved on the board: {exc}; the values hold until reset")
    else:
        say(f"  set on the board (not saved): {on_board}")

    if robot is not None:
        # the robot back on its wheels, the pendulum held upright until the board balances
        robot.do("hold", phi=0.0, cart="still", until="driving")
    values = {"pot_offset": res["pot_offset"], "pot_range": round(res["pot_range"], 6), "enc_cpr": res["enc_cpr"]}
    note = (f"calibrated by `upright board calibrate` on {time.strftime('%Y-%m-%d %H:%M')}: adc_sign "
            f"{res['adc_sign']:+d}, enc_sign {res['enc_sign']:+d}, motor_sign {res['motor_sign']:+d} (board parameters)")
    text = robot_toml(src.read_text(), values, note)
    out = Path(robot_out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    load_params(out)  # the file must load as a robot (bad values are refused by key)
    say(f"  wrote {out}: [sensors] pot_offset {values['pot_offset']}, pot_range {values['pot_range']}, "
        f"enc_cpr {values['enc_cpr']}")
    return res


def _wait_wheels_still(board: Board, say: Callable[[str], None], timeout: float = 30.0) -> None:
    """Wait (up to ``timeout`` wall seconds: :data:`WHEELS_STILL_S` of the board's clock) until the
    lifted wheels stop after the motor step.

    A save pauses the board's loop for a flash write (some 20 ms): wheels still coasting then turn
    more counts between two reads than the cart can move in one tick, and the board latches
    ``enc_jump``.  Still means the encoder unchanged over three reads in a row.
    """
    t_end = time.monotonic() + timeout
    last, same = None, 0
    while time.monotonic() < t_end:
        e = int(board.raw_sensors()["enc"]) & 0xFFFF
        same = same + 1 if e == last else 0
        if same >= 3:
            return
        last = e
        time.sleep(0.05)
    say(f"  the wheels still turn after {timeout:.0f} s: saving anyway (stop them by hand if `enc_jump` latches)")


def _motor_sign(board: Board, ask: Ask, say: Callable[[str], None], res: dict[str, Any], test_duty: int,
                step: Callable[..., dict[str, Any]], by_robot: bool) -> int:
    table = param_table()
    sign = res["motor_sign"]
    old_duty = board.param_get("max_duty")
    board.param_set("max_duty", min(old_duty, test_duty))
    try:
        step(f"Step 4/4: WHEELS LIFTED. Press Enter to arm (max_duty {min(old_duty, test_duty)}), "
             "then hold the pendulum upright", "hold", phi=0.0, cart="free")
        st = board.state(fresh=True)
        if st["faults"]:
            board.clear_faults()
        board.arm()
        a = sample(board, 0.2, keepalive=True)

        def idle() -> None:
            board.keepalive()
            board.poll(0.02)

        moved = step("Step 4/4: tilt the pendulum slightly FORWARD and hold it about a second, then press Enter",
                     "hold", idle, phi=-MOTOR_TILT_RAD, cart="free", seconds=1.0)
        b = sample(board, 0.3, keepalive=True)
        state = board.state(fresh=True)
    finally:
        board.safe_disarm()
        board.param_set("max_duty", old_duty)
    de = _enc_delta(a["enc_raw_last"], b["enc_raw_last"]) * res["enc_sign"]
    say(f"  armed and tilted: the encoder moved {de:+d} counts forward (board {state['state_name']})")
    if abs(de) >= 20:
        ok = de > 0
    elif by_robot:
        ok = float(moved.get("moved_m", 0.0)) > 0  # the robot saw its wheels turn
    else:
        ans = ask("Did the wheels turn so as to drive the cart FORWARD, towards the tilt? [y/n]", None)
        ok = ans.strip().lower().startswith("y")
    if not ok:
        sign = -sign
        say(f"  wheels drove away from the tilt: motor_sign flipped to {sign:+d}"
            + ("" if "motor_sign" in table else " (set MOTOR_SIGN in firmware/board.py: this firmware has no "
                                                 "motor_sign parameter)"))
    else:
        say(f"  wheels drive towards the tilt: motor_sign {sign:+d} is right")
    return sign
