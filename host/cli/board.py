"""``upright board``: operate a board -- status, arm, parameters, gains, recording, calibration.

Works the same on a real board (``--port /dev/ttyUSB0``), on the emulated Pico
(``upright emulate rp2040 --pty`` prints the port) and on the virtual board
(:mod:`host.boards.vport`).  Examples::

    upright board --port /dev/ttyUSB0 status [--watch] [--json]
    upright board --port /dev/ttyUSB0 arm --seconds 30       # host heartbeat while armed; Ctrl-C disarms
    upright board --port /dev/ttyUSB0 params get max_duty
    upright board --port /dev/ttyUSB0 params set max_duty 8000
    upright board --port /dev/ttyUSB0 gains upload --params robot.toml --save
    upright board --port /dev/ttyUSB0 log --seconds 10 --out run.parquet
    upright board --port /dev/ttyUSB0 calibrate --out robot.toml
    upright board --port /dev/ttyUSB0 excite --seconds 20 --amplitude 0.5 --out bal.csv
    upright board params list                                  # the parameter table, no board needed
    upright board --port /dev/ttyUSB0 excite --cart-only --seconds 8 --amplitude 1 --out cart.csv
    upright board --port /dev/ttyUSB0 mode hil                 # robot | hil | repl, no reflash

One port, many tools: the first tool on a port holds it and serves it to the others through
a local hub (:mod:`host.link.porthub`), so ``status`` or ``log`` work while ``arm`` or the
dashboard runs; a port held by another program is refused in one line naming its PID.
``--seconds`` is wall-clock time on this host, not board time.

Exit status: 0 done, 1 the board failed/refused/did not answer or the link was lost, 2 bad input
(a parameter name or value outside the table, a read-only parameter, a file), 130 Ctrl-C,
143 SIGTERM, 129 SIGHUP (a closed terminal) -- each after disarming the board where it can
still be reached and closing every recording with all its rows.
"""

from __future__ import annotations

import argparse
import json
import select
import sys
import time
from typing import Any, Callable

from host.cli import args as A

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright board``."""
    parser.add_argument("--port", metavar="DEV",
                        help="serial device or pty (a CAN channel with --link can); required but for `params list`. "
                             "One tool per port: a second one is told which process holds it")
    parser.add_argument("--link", choices=("serial", "can"), default="serial", help="framing (default serial)")
    parser.add_argument("--baudrate", "--baud", dest="baudrate", type=A.positive_int, default=A.board_baud(),
                        help=f"serial line rate (default {A.board_baud()}: firmware/board.py UART_BAUD; "
                             "--baud is the old spelling)")
    parser.add_argument("--node", type=A.int_range(0, 63), default=1, help="CAN node id (default 1)")
    parser.add_argument("--can-interface", type=A.can_interface, default="slcan", metavar="NAME",
                        help="python-can interface with --link can (default slcan)")
    parser.add_argument("--timeout", type=A.in_range(0.01, 60), default=None, metavar="S",
                        help="seconds per request attempt (3 retries; default 0.3 scaled by the board's clock, "
                             "measured against the wall's once it answers: an emulated board at 0.15x gets 2 s)")
    parser.add_argument("--answer-timeout", type=A.in_range(0.1, 600), default=10.0, metavar="S",
                        help="seconds for the board to answer at all (default 10)")
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)

    sp = sub.add_parser("status", help="identity, state, fault flags, heartbeat rate, link statistics")
    sp.add_argument("--json", action="store_true", help="one JSON object on stdout")
    sp.add_argument("--watch", action="store_true", help="live view, refreshed until Ctrl-C")
    sp.add_argument("--interval", type=A.in_range(0.1, 60), default=0.5, help="--watch refresh period (s)")

    sp = sub.add_parser("arm", help="arm and keep the host heartbeat going; disarm on Ctrl-C, exit or --seconds")
    sp.add_argument("--seconds", type=A.in_range(0, 86400, lo_open=True), default=None,
                    help="disarm after this many wall-clock seconds (default: until Ctrl-C, SIGTERM or SIGHUP, "
                         "which disarm too)")
    sp.add_argument("--clear", action="store_true", help="clear latched faults first")
    sub.add_parser("disarm", help="disarm (motor off)")
    sub.add_parser("clear", help="clear latched faults (while disarmed)")
    sp = sub.add_parser("mode", help="what the board runs on its link: robot (at boot), hil, repl (mpremote on USB)")
    sp.add_argument("mode", choices=("robot", "hil", "repl"))

    sp = sub.add_parser("params", help="parameters by name, with units and ranges from the parameter table")
    psub = sp.add_subparsers(dest="params_action", metavar="get|set|save|list", required=True)
    g = psub.add_parser("get", help="read parameters (all without a name)")
    g.add_argument("names", nargs="*", metavar="NAME")
    g.add_argument("--json", action="store_true")
    s = psub.add_parser("set", help="write a parameter")
    s.add_argument("name", metavar="NAME")
    s.add_argument("value", metavar="VALUE")
    psub.add_parser("save", help="persist parameters and gain table on the board")
    psub.add_parser("list", help="the parameter table: names, units, ranges, defaults (no board needed)")

    sp = sub.add_parser("gains", help="gain tables")
    gsub = sp.add_subparsers(dest="gains_action", metavar="upload", required=True)
    u = gsub.add_parser("upload", help="upload a table (a file or a design), read its CRC back")
    u.add_argument("file", nargs="?", metavar="FILE", help=".py gain module (upright export --out) or .bin")
    u.add_argument("--design", action="store_true", help="the shipped design (default without FILE)")
    u.add_argument("--params", metavar="TOML", help="robot parameters for --design (upright board calibrate writes one)")
    u.add_argument("--save", action="store_true", help="persist it on the board")

    sp = sub.add_parser("log", help="record telemetry to CSV or Parquet")
    _record_args(sp)

    sp = sub.add_parser("calibrate", help="guided commissioning: offsets, scales and signs; robot TOML + board params")
    sp.add_argument("--out", default="robot.toml", metavar="TOML", help="robot file to write (default robot.toml)")
    sp.add_argument("--params", metavar="TOML", help="robot file to start from (default sim/robot.toml)")
    sp.add_argument("--tilt-deg", type=A.in_range(2, 45), default=10.0, help="tilt of step 2 (degrees, default 10)")
    sp.add_argument("--move-cm", type=A.in_range(1, 200), default=10.0, help="roll of step 3 (cm, default 10)")
    sp.add_argument("--yes", action="store_true", help="do not wait for Enter (scripted runs)")
    sp.add_argument("--no-motor", action="store_true", help="skip the motor-sign step")
    sp.add_argument("--no-save", action="store_true", help="set the parameters on the board but do not persist them")
    sp.add_argument("--robot", default="auto", metavar="auto|person|SOCKET", help=_robot_help())

    sp = sub.add_parser("excite", help="the firmware's PRBS on the cart force (upright identify), recorded")
    _record_args(sp)
    sp.add_argument("--amplitude", type=A.in_range(0, 10, lo_open=True), default=0.5,
                    help="N (default 0.5; the board refuses more than half its force clamp)")
    sp.add_argument("--div", type=A.int_range(1, 255), default=4, help="control ticks per PRBS bit (default 4)")
    sp.add_argument("--cart-only", action="store_true",
                    help="pendulum removed/locked: PRBS open loop, then disarm and record the coast-down")
    sp.add_argument("--coast", type=A.in_range(0.5, 60), default=3.0,
                    help="--cart-only: coast-down, wall-clock s (default 3)")
    sp.add_argument("--board-seconds", type=A.in_range(0, 3600, lo_open=True), default=None, metavar="S",
                    help="excite for S seconds of the BOARD's clock (counted in its ticks) instead of --seconds "
                         "of wall time: the same log on a board slower than real time (the emulated Pico)")
    sp.add_argument("--board-coast", type=A.in_range(0.5, 600), default=None, metavar="S",
                    help="--cart-only: the coast-down in board seconds instead of --coast")
    sp.add_argument("--arm", dest="arm_flag", action="store_true",
                    help="deprecated, does nothing: arming first and disarming at the end is the default "
                         "(--no-arm for a board that already balances)")
    sp.add_argument("--no-arm", dest="arm", action="store_false", default=True,
                    help="the board is already balancing (armed by another tool): do not arm or disarm")


def _record_args(sp: argparse.ArgumentParser) -> None:
    sp.add_argument("--seconds", type=A.in_range(0, 86400, lo_open=True), default=10.0,
                    help="how long, in wall-clock seconds on this host (default 10 s) -- not board time: a "
                         "board slower than real time (the emulated Pico) records fewer ticks in it")
    sp.add_argument("--out", required=True, metavar="FILE", help=".csv or .parquet")
    sp.add_argument("--quiet", action="store_true", help="no progress bar")


def _robot_help() -> str:
    from host.operate.calibrate import ROBOT_HELP

    return ROBOT_HELP


# ------------------------------------------------------------------ helpers
def _say(text: str = "") -> None:
    try:
        print(text, flush=True)
    except (OSError, ValueError):  # a closed terminal must not stop the disarm that follows
        pass


def _err(text: str) -> None:
    try:
        print(text, file=sys.stderr, flush=True)
    except (OSError, ValueError):
        pass


def _bar(k: float, n: float, extra: str = "", width: int = 30) -> None:
    frac = 0.0 if n <= 0 else max(0.0, min(1.0, k / n))
    fill = int(width * frac)
    tty = sys.stderr.isatty()
    line = f"[{'#' * fill}{'.' * (width - fill)}] {100 * frac:3.0f}% {k:5.1f}/{n:g} s {extra}"
    try:
        sys.stderr.write(("\r" + line) if tty else (line + "\n"))
        sys.stderr.flush()
    except (OSError, ValueError):  # a closed terminal: the run (and its disarm) goes on
        pass


def _open(args: argparse.Namespace) -> Any:
    from host.operate.board import Board

    b = Board.open(args.port, link=args.link, baudrate=args.baudrate, node=args.node,
                   can_interface=args.can_interface, timeout=args.timeout, answer_timeout=args.answer_timeout)
    if args.timeout is None and b.speed < 0.9:
        # a board slower than real time (the emulated Pico): every wait scaled by its clock
        _err(f"upright board: board clock at {b.speed:.2f}x the wall's: {b.timeout:.1f} s per request attempt "
             "(--timeout fixes it)")
    if getattr(b.link, "via_hub", False):
        who = "; ".join(f"PID {pid} ({cmd})" for pid, cmd in b.link.hub_owner) or "another upright tool"
        _err(f"upright board: {args.port} is held by {who}: sharing the board through its hub")
    return b


def _fmt_hash(v: Any) -> str:
    return f"{v:#06x}" if isinstance(v, int) else "-"


def render_status(st: dict[str, Any]) -> str:
    """The status dict as a few lines of text."""
    from host.operate.board import fault_table

    idn = st["identity"]
    hb = st["heartbeat"]
    lines = [f"board on {st['port']}"]
    if idn.get("version_message"):
        match = idn.get("table_match")
        lines.append(f"  firmware {idn.get('fw_version_text', idn.get('fw_version'))}  message table "
                     f"{_fmt_hash(idn.get('table_hash'))} ({'matches this host' if match else 'DIFFERS'})  "
                     f"params {_fmt_hash(idn.get('param_hash'))}  gains CRC {_fmt_hash(idn.get('gains_crc'))}  "
                     f"reset cause {idn.get('reset_cause_name', idn.get('reset_cause'))}")
    else:
        crc8 = hb.get("gains_crc")
        lines.append("  identity: this firmware has no VERSION message" +
                     (f"; gains CRC low byte {crc8:#04x}" if isinstance(crc8, int) else ""))
    lines.append(f"  state {st['state']}  boot {hb.get('boot')}{_mod_text('boot')}  {uptime_text(st)}"
                 + f"  arming epoch {hb.get('epoch', '-')}")
    bst = st.get("board_status", {})
    if bst:
        extra = []
        if "starts" in bst:
            extra.append(f"control loop started {bst['starts']} time(s) since boot"
                         + (" (MODE switches back to the robot, no reset)" if bst["starts"] > 1 else ""))
        if "cfg_slot" in bst:
            slot = bst["cfg_slot"]
            extra.append("saved configuration: " + ("none (defaults)" if slot < 0 else
                                                    f"copy {'ab'[slot] if slot in (0, 1) else slot}, "
                                                    f"sequence {bst.get('cfg_seq', '?')}"))
        rest = {k: v for k, v in bst.items() if k not in ("uptime_ms", "starts", "cfg_slot", "cfg_seq")}
        if rest:
            extra.append(", ".join(f"{k} {v}" for k, v in rest.items()))
        lines.extend("  " + e for e in extra)
    if st["faults"]:
        ft = fault_table()
        lines.append(f"  faults {st['faults']:#x}:")
        for bit, (name, doc) in ft.items():
            if st["faults"] & bit:
                lines.append(f"    {name:10s} {doc}")
    else:
        lines.append("  faults none")
    rate = st["heartbeat_hz"]
    lines.append(f"  heartbeat {rate:.1f} Hz" if rate else "  heartbeat rate: fewer than two heartbeats seen")
    lk = st["link"]
    drops = ", ".join(f"{k} {v}" for k, v in lk["drops"].items() if v) or "none"
    joined = f" (joined mid-frame: {lk['joined_bytes']} bytes skipped)" if lk.get("joined_bytes") else ""
    lines.append(f"  link: {lk['sent']} frames sent, {lk['received']} received, host drops {drops}{joined}")
    bs = st.get("board_stats", {})
    if "decode" in bs:
        d = bs["decode"]
        lines.append("  board decoder drops: " + ", ".join(f"{k} {v}" for k, v in d.items()))
    if "frames" in bs:
        lines.append(f"  board frames: {bs['frames'].get('frames_in')} in, {bs['frames'].get('frames_out')} out")
    if "loop" in bs:
        lp = bs["loop"]
        lines.append("  board loop: " + ", ".join(f"{k} {v:g}" for k, v in lp.items()))
    if "timing" in bs:
        tm = bs["timing"]
        lines.append("  timing: " + ", ".join(f"{k} {v}" for k, v in tm.items()))
    return "\n".join(lines)


def _field(name: str, message: str | None = None) -> Any:
    # the field of this name in ``message``, or the widest of that name in the table
    from host.link import messages as M

    best = None
    classes = [M.BY_NAME[message]] if message in M.BY_NAME else M.MESSAGES.values()
    for cls in classes:
        for f in cls.FIELDS:
            if f.name == name and not f.is_raw and (best is None or f.size > best.size):
                best = f
    return best


def _mod_text(name: str) -> str:
    # " (mod 256)" for a counter the table carries in one byte
    f = _field(name)
    return f" (mod {1 << (8 * f.size)})" if f is not None and f.size < 2 else ""


def _duration_text(s: float) -> str:
    if s < 120:
        return f"{s:.1f} s"
    m, sec = divmod(int(s), 60)
    h, m = divmod(m, 60)
    return f"{h} h {m:02d} min {sec:02d} s" if h else f"{m} min {sec:02d} s"


def uptime_text(st: dict[str, Any]) -> str:
    """The board's uptime as it reports it: the widest ``uptime*`` field of its heartbeat or
    identity, and ``(mod N s)`` when the field wraps within a day (the heartbeat's 16-bit
    ``uptime_ms`` wraps every 65.5 s: 67 s reads "1.5 s (mod 65.5 s)", not a reboot)."""
    best: tuple[int, float, float] | None = None  # (bits, seconds, wrap s)
    full = st.get("board_status", {}).get("uptime_ms")
    if isinstance(full, int):
        # the board's own figure in full (msgtable STATUS, an int below 2**30 ms: 12.4 days): it
        # wins over any heartbeat field (whose name, uptime_ms, the 32-bit SESSION field shares)
        return f"uptime {_duration_text(full / 1000.0)}"
    for msg, src in (("heartbeat", st.get("heartbeat", {})), ("version", st.get("identity", {}))):
        for k, v in src.items():
            if not k.startswith("uptime") or not isinstance(v, (int, float)):
                continue
            f = _field(k, msg)
            if f is None:
                continue
            unit = {"ms": 1e-3, "s": 1.0, "us": 1e-6}.get(f.unit, 1e-3)
            bits = 8 * f.size
            # v is physical (scale applied); the wrap is in raw counts
            wrap = (1 << bits) * f.scale * unit
            if best is None or bits > best[0]:
                best = (bits, float(v) * unit, wrap)
    if best is None:
        return "uptime -"
    bits, secs, wrap = best
    if wrap < 86400:
        return f"uptime {_duration_text(secs)} (mod {wrap:.1f} s: the board sends its low {bits} bits)"
    return f"uptime {_duration_text(secs)}"


# ------------------------------------------------------------------ actions
def _status(b: Any, args: argparse.Namespace) -> int:
    if not args.watch:
        st = b.status(listen=1.0)
        if args.json:
            print(json.dumps(st, indent=2, default=str))
        else:
            _say(render_status(st))
        return 0
    tty = sys.stdout.isatty()
    b.poll(0.2)
    while True:
        st = b.status(listen=args.interval)
        text = render_status(st)
        if args.json:
            print(json.dumps(st, default=str), flush=True)
        elif tty:
            sys.stdout.write("\x1b[H\x1b[2J" + text + "\n\n(Ctrl-C to stop)\n")
            sys.stdout.flush()
        else:
            _say(text)


def _hold_armed(b: Any, seconds: float | None, tick: Callable[[float], None] | None = None) -> str:
    """Keep the host heartbeat going while armed; returns why it ended.

    Ctrl-C, SIGTERM and SIGHUP (a closed terminal) end it the same way: the loop raises
    KeyboardInterrupt (:class:`host.cli.args.Terminated` for the two others) between two
    link calls, and the caller disarms.
    """
    import signal
    import threading

    from host.cli.main import TERMINATING, note_signal
    from host.link import messages as M

    # a signal sets a flag the loop checks between link calls: a KeyboardInterrupt raised inside
    # the link (holding its lock, half a frame written) could leave the disarm that follows stuck
    stop = threading.Event()
    got: list[int] = []

    def on_signal(signum: int, _frame: object) -> None:
        note_signal(signum)
        got.append(signum)
        stop.set()

    prev: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for s in (signal.SIGINT, *TERMINATING):
            if s == signal.SIGINT or signal.getsignal(s) is not signal.SIG_IGN:
                prev[s] = signal.signal(s, on_signal)
    try:
        return _hold_loop(b, seconds, tick, stop, M, got)
    finally:
        for s, h in prev.items():
            signal.signal(s, h)


def _hold_loop(b: Any, seconds: float | None, tick: Callable[[float], None] | None, stop: Any, M: Any,
               got: list[int]) -> str:
    import signal

    t0 = time.monotonic()
    last_state = None
    armed_seen = False
    while True:
        if stop.is_set():
            if got and got[0] != signal.SIGINT:
                raise A.Terminated(got[0])
            raise KeyboardInterrupt
        b.keepalive()
        b.poll(0.02)
        el = time.monotonic() - t0
        hb = b.heartbeat
        if hb is not None:
            name = M.STATES.get(hb.state, str(hb.state))
            if name == "disarmed" and not armed_seen:
                # a heartbeat the board sent before it took the arm (the last one polled, or one
                # still on the line): not news
                pass
            elif name != last_state:
                _err(f"upright board: {name}")
                last_state = name
            if name != "disarmed":
                armed_seen = True
            if name == "fault":
                from host.operate.board import fault_names

                return "fault: " + ",".join(fault_names(hb.faults))
            if name == "disarmed" and armed_seen:
                return "disarmed by another host"
        if tick is not None:
            tick(el)
        if seconds is not None and el >= seconds:
            return "time"


def _arm(b: Any, args: argparse.Namespace) -> int:
    from host.cli.args import RunFailed

    if args.clear:
        b.clear_faults()
    b.arm()
    _err(f"upright board: armed; host heartbeat running ({'for %g s' % args.seconds if args.seconds else 'Ctrl-C'}"
         " disarms)")
    why = _hold_armed(b, args.seconds)
    b.disarm()
    _err("upright board: disarmed" + (" (by another host)" if why.startswith("disarmed") else ""))
    if why.startswith("fault"):
        raise RunFailed(f"the board latched a fault while armed ({why[7:]})")
    return 0


def _params(b: Any, args: argparse.Namespace) -> int:
    from host.operate.board import param_info, param_table

    act = args.params_action
    if act == "list":
        _params_list()
        return 0
    if act == "get":
        names = args.names or list(param_table())
        for n in names:
            param_info(n)
        vals = {n: b.param_get(n) for n in names}
        if args.json:
            print(json.dumps(vals, indent=2))
        else:
            for n, v in vals.items():
                p = param_info(n)
                _say(f"{n:18s} {v} {p['unit']}".rstrip() + f"    ({p['min']}..{p['max']}, default {p['default']})")
        return 0
    if act == "set":
        v = b.param_set(args.name, args.value)
        p = param_info(args.name)
        _say(f"{args.name} = {v} {p['unit']}".rstrip())
        return 0
    name = b.save()
    _say(f"saved on the board ({name})")
    return 0


def _params_list() -> None:
    # the host's own parameter table (firmware/msgtable.py PARAMS): no board needed
    from host.operate.board import param_read_only, param_table

    for name, p in param_table().items():
        ro = "  [read-only]" if param_read_only(name) is not None else ""
        _say(f"{name:18s} {p['unit'] or '-':6s} {p['min']}..{p['max']} (default {p['default']}){ro}  {p['doc']}")


def _gains(b: Any, args: argparse.Namespace) -> int:
    from host.cli.args import UsageError
    from host.operate.board import NotSupported, gains_blob_from_design, gains_blob_from_file

    if args.file and (args.design or args.params):
        raise UsageError("gains upload: give FILE or --design/--params, not both")
    if args.file:
        blob, label = gains_blob_from_file(args.file), args.file
    else:
        blob, label = gains_blob_from_design(args.params)
    res = b.upload_gains(blob)
    crc = res["crc"]
    if res["verified"] is None:
        _say(f"uploaded {label}: {res['nbytes']} bytes, CRC {crc:#06x} (this firmware reports no CRC to read back)")
    else:
        back = res.get("board_crc")
        back_txt = f"{back:#06x}" if back is not None else f"low byte {res.get('board_crc_low8'):#04x}"
        _say(f"uploaded {label}: {res['nbytes']} bytes, CRC {crc:#06x}; board reports {back_txt}: verified")
    if args.save:
        try:
            _say(f"saved on the board ({b.save()})")
        except NotSupported as exc:
            _say(f"not saved: {exc}")
    return 0


def _record(b: Any, args: argparse.Namespace) -> int:
    from host.cli.args import RunFailed
    from host.cli.main import interrupted
    from host.operate.board import BoardError
    from host.operate.record import Recorder

    rec = Recorder(b, args.out)
    failure: str | None = None
    t0 = time.monotonic()
    last_bar = -1.0
    try:
        while True:
            el = time.monotonic() - t0
            if el >= args.seconds:
                break
            if b.armed_by_us:
                b.keepalive()
            b.poll(0.02)
            if not args.quiet and el - last_bar >= 0.25:
                last_bar = el
                _bar(el, args.seconds, f"{rec.rows} rows, {rec.lost} lost")
        if not args.quiet:
            _bar(args.seconds, args.seconds, f"{rec.rows} rows, {rec.lost} lost")
            if sys.stderr.isatty():
                sys.stderr.write("\n")
    except BoardError as exc:
        failure = str(exc)
    finally:
        rec.close()
        s = rec.summary()
        msg = (f"upright board: {s['rows']} rows ({s['telemetry_frames']} telemetry frames) to {s['file']}; "
               f"{s['lost']} lost")
        _err(msg)
    if failure is not None:
        if interrupted():
            raise KeyboardInterrupt
        raise RunFailed(f"{failure} (kept {rec.rows} rows in {args.out})")
    return 0


def _excite(b: Any, args: argparse.Namespace) -> int:
    from host.cli.args import RunFailed
    from host.cli.main import interrupted
    from host.operate.board import BoardError
    from host.operate.excite import run_excite

    def progress(el: float, total: float, rec: Any) -> None:
        if not args.quiet:
            _bar(el, total, f"{rec.rows} rows, {rec.lost} lost")

    try:
        s = run_excite(b, args.out, seconds=args.seconds, amplitude_n=args.amplitude, div=args.div,
                       cart_only=args.cart_only, coast_s=args.coast, arm=args.arm,
                       board_seconds=args.board_seconds, board_coast_s=args.board_coast, progress=progress)
    except BoardError as exc:
        if interrupted():
            raise KeyboardInterrupt from exc
        raise RunFailed(str(exc)) from exc
    if not args.quiet and sys.stderr.isatty():
        sys.stderr.write("\n")
    # the warning before the summary: the summary stays the last line
    if s.get("moved") is False:
        x0, phi0 = s["span"]["x"][0], s["span"]["phi"][0]
        _err(f"upright board: warning: nothing moved -- x ({x0:g} m) and phi ({phi0:g} rad) were the same in every "
             "excited row: is the motor supply on, the driver enabled, are the encoder and pot wired? "
             "`upright identify` cannot use this log")
    _err(f"upright board: {s['rows']} rows ({s['telemetry_frames']} telemetry frames) to {s['file']}; "
         f"{s['lost']} lost; excitation {'cart-only' if args.cart_only else 'balancing'} "
         f"+-{args.amplitude:g} N, {args.div} ticks per bit" + _board_time(s))
    return 0


def _board_time(s: dict[str, Any]) -> str:
    # the board time the log holds (its ticks / loop rate): what upright identify needs
    if s.get("board_s") is None:
        return ""
    co = f" + {s['coast_board_s']:.2f} s coasting" if s.get("coast_board_s") is not None else ""
    return f"; {s['board_s']:.2f} s of board time excited{co}"


def _ask_factory(args: argparse.Namespace) -> Callable[..., str]:
    def ask(prompt: str, idle: Callable[[], None] | None = None) -> str:
        print(prompt, flush=True)
        if args.yes:
            return "y" if prompt.rstrip().endswith("[y/n]") else ""
        buf = b""
        fd = sys.stdin.fileno()
        while True:
            r = select.select([fd], [], [], 0.05)[0]
            if r:
                import os

                chunk = os.read(fd, 1024)
                if not chunk:
                    raise A.RunFailed("end of input while waiting for an answer")
                buf += chunk
                if b"\n" in buf:
                    return buf.split(b"\n", 1)[0].decode(errors="replace")
            elif idle is not None:
                idle()
    return ask


def _calibrate(b: Any, args: argparse.Namespace) -> int:
    from host.operate.calibrate import robot_hands, run_calibration

    A.check_out_file(args.out, "--out")
    key = f"can:{args.can_interface}:{args.port}" if args.link == "can" else args.port
    robot = robot_hands(args.robot, key)
    if robot is not None:
        _say(f"the virtual robot on {args.port} does the steps that need a person (its hands: {robot.path}; "
             "--robot person prompts instead)")
    try:
        res = run_calibration(b, _ask_factory(args), _say, robot_in=args.params, robot_out=args.out,
                              tilt_deg=args.tilt_deg, move_m=args.move_cm / 100, motor_check=not args.no_motor,
                              save=not args.no_save, robot=robot)
    finally:
        if robot is not None:
            robot.close()
    _say(f"calibration written to {res['robot_out']}; next: upright board --port {args.port} gains upload "
         f"--params {res['robot_out']} --save")
    return 0


ACTIONS: dict[str, Callable[[Any, argparse.Namespace], int]] = {
    "status": _status, "arm": _arm, "disarm": lambda b, a: (b.disarm(), _say("disarmed"))[1] or 0,
    "clear": lambda b, a: (b.clear_faults(), _say("faults cleared"))[1] or 0,
    "mode": lambda b, a: (b.set_mode(a.mode), _say(f"mode {a.mode}"))[1] or 0,
    "params": _params, "gains": _gains, "log": _record,
    "excite": _excite, "calibrate": _calibrate,
}


def run(args: argparse.Namespace) -> int:
    """Run ``upright board``."""
    from host.operate.board import BoardError, ParamInputError, check_param, param_info
    from host.operate.record import format_of

    if args.action == "params" and args.params_action == "list":
        _params_list()
        return 0
    if not args.port:
        raise A.UsageError("--port is required (the board's serial device, pty or CAN channel)")
    if args.action == "excite" and args.arm_flag:
        _err("upright board: note: excite --arm is deprecated and does nothing: arming first is the default "
             "(--no-arm for a board that already balances)")
    # bad input is refused before the board is touched
    try:
        if args.action == "gains" and args.file and (args.design or args.params):
            # the conflict first: FILE's contents do not matter when it cannot be used
            raise A.UsageError(f"gains upload: give FILE ({args.file}) or --design/--params, not both")
        if args.action in ("log", "excite"):
            A.check_out_file(args.out, "--out")
            format_of(args.out)
        if args.action == "excite" and args.board_coast is not None and not args.cart_only:
            raise A.UsageError("--board-coast is the coast-down of a --cart-only run: give --cart-only too")
        if args.action == "params" and args.params_action == "set":
            check_param(args.name, args.value)
        if args.action == "params" and args.params_action == "get":
            for n in args.names:
                param_info(n)
        if args.action == "gains" and args.file:
            from host.operate.board import gains_blob_from_file

            gains_blob_from_file(args.file)
        if args.action == "gains" and args.params:
            from sim.params import load_params

            load_params(args.params)
    except (ParamInputError, ValueError) as exc:
        if isinstance(exc, A.UsageError):
            raise
        raise A.UsageError(str(exc)) from None
    b = _open(args)
    try:
        try:
            return int(ACTIONS[args.action](b, args) or 0)
        except ParamInputError as exc:
            raise A.UsageError(str(exc)) from None
        except KeyboardInterrupt:
            if b.armed_by_us:
                ok = b.safe_disarm()
                _err("upright board: " + ("disarmed" if ok else "could not reach the board to disarm it"))
            raise
    except BoardError as exc:
        if b.armed_by_us:
            ok = b.safe_disarm()
            _err("upright board: " + ("disarmed" if ok else "could not reach the board to disarm it"))
        raise A.RunFailed(str(exc)) from None
    finally:
        b.close()
