"""``upright dashboard``: a live web page for a board -- plots, state, arm/disarm, reference, gains, recording.

::

    upright dashboard --virtual                    # the firmware on a pty, balancing the simulated robot
    upright dashboard --port /dev/ttyUSB0          # a board (its link at the board's UART rate)
    upright dashboard --emulate rp2040             # the emulated Pico (``upright emulate rp2040 --pty``)

Prints the page's address (``http://127.0.0.1:8765/?token=...``) on stdout, one line, and
serves until Ctrl-C, SIGTERM or SIGHUP (a closed terminal), or ``--seconds``.  The address
carries this run's random token: the page is served only with it, and the server takes board
commands only from that page (``host/dashboard/server.py``), not from any other local
process.  Everything the page loads is served from the project (uPlot from ``node_modules``).
The dashboard keeps the board's watchdog fed only while a page is open and the arm was asked
from it; when the last page closes it stops and disarms the board.  On exit -- by any of those
signals, or ``--seconds`` -- it disarms the board before anything else, waits (up to 3 s) for
the board's own word that it is disarmed and says so in one line on stderr; further signals
during that are ignored.  Exit status 130 after Ctrl-C, 128 + the signal's number after SIGTERM
(143) or SIGHUP (129).  Recordings go to ``--record-dir`` (CSV, one row per telemetry frame)
and download from the page.
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from host.cli import args as A

__all__ = ["add_arguments", "run", "SHUTDOWN_SIGNALS"]

SHUTDOWN_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
"""Signals (besides SIGINT, Ctrl-C) that end the dashboard the way Ctrl-C does: board disarmed first."""
_CONFIRM_S = 3.0


class _Signalled(BaseException):
    """SIGTERM or SIGHUP reached the dashboard (a BaseException, like KeyboardInterrupt: nothing
    on the way out swallows it)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _on_signal(signum: int, frame: object) -> None:
    raise _Signalled(signum)


def _install(handler: Any, signums: tuple[int, ...]) -> dict[int, Any]:
    old = {}
    for s in signums:
        try:
            old[s] = signal.signal(s, handler)
        except (ValueError, OSError):  # pragma: no cover - not the main thread
            pass
    return old


def _restore(old: dict[int, Any]) -> None:
    for s, h in old.items():
        try:
            signal.signal(s, h)
        except (ValueError, OSError, TypeError):  # pragma: no cover
            pass


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright dashboard``."""
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--virtual", action="store_true",
                       help="start the virtual board (the firmware under MicroPython on a pty) and the simulated robot")
    where.add_argument("--port", metavar="DEV",
                       help="a board's serial port (/dev/ttyUSB0, a pty) or can:INTERFACE:CHANNEL")
    where.add_argument("--emulate", choices=("rp2040",), metavar="BOARD",
                       help="start the emulated board (rp2040) and connect to its host link")
    parser.add_argument("--http-port", type=A.int_range(0, 65535), default=8765, metavar="N",
                        help="port of the page on 127.0.0.1 (default 8765; 0 = any free port)")
    parser.add_argument("--baudrate", "--baud", type=A.positive_int, default=A.board_baud(),
                        help=f"serial baud rate (default {A.board_baud()}: firmware/board.py UART_BAUD)")
    parser.add_argument("--node", type=A.int_range(0, 63), default=1, help="CAN node id (default 1)")
    parser.add_argument("--record-dir", default="out/dashboard", metavar="DIR",
                        help="where recordings are written (default out/dashboard)")
    parser.add_argument("--seconds", type=A.positive, default=None, metavar="S",
                        help="stop after S seconds (default: serve until Ctrl-C)")


def _start_emulator() -> tuple[subprocess.Popen[bytes], str]:
    # `upright emulate rp2040 --pty` in its own process: its first stdout line is the port
    import select

    proc = subprocess.Popen([sys.executable, "-m", "host.cli.main", "emulate", "rp2040", "--pty"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None
    deadline = time.monotonic() + 120.0
    line = b""
    while time.monotonic() < deadline:
        if select.select([proc.stdout], [], [], 0.2)[0]:
            line = proc.stdout.readline()
            break
        if proc.poll() is not None:
            break
    port = line.decode(errors="replace").strip()
    if not port.startswith("/dev/"):
        proc.kill()
        err = (proc.stderr.read() if proc.stderr else b"").decode(errors="replace").strip().splitlines()
        raise A.RunFailed(f"the emulated board did not start: {err[-1] if err else 'no port printed'}")
    return proc, port


def run(args: argparse.Namespace) -> int:
    """Run ``upright dashboard`` (SIGTERM and SIGHUP end it as Ctrl-C does: board disarmed first)."""
    old = _install(_on_signal, SHUTDOWN_SIGNALS)
    try:
        return _serve(args)
    except _Signalled as sig:
        name = signal.Signals(sig.signum).name
        print(f"upright dashboard: {name}: stopped", file=sys.stderr, flush=True)
        return 128 + sig.signum
    finally:
        _restore(old)


def _serve(args: argparse.Namespace) -> int:
    from host.dashboard.hub import Hub, PlainPump
    from host.dashboard.server import VENDOR, DashboardServer
    from host.link.clients import LinkError, open_link

    record_dir = A.check_out_dir(args.record_dir, "--record-dir")
    if not (VENDOR / "uPlot.iife.min.js").is_file():
        raise A.RunFailed(f"{VENDOR}/uPlot.iife.min.js is missing: run `make setup` (npm ci)")
    emu: subprocess.Popen[bytes] | None = None
    plant: Any = None
    pump: PlainPump | None = None
    link: Any = None
    hub: Hub | None = None
    server: DashboardServer | None = None
    try:
        if args.virtual:
            from host.dashboard.plant import VirtualPlant

            print("upright dashboard: starting the virtual board...", file=sys.stderr, flush=True)
            plant = VirtualPlant()
            hub = Hub(plant.open(), {"mode": "virtual", "port": plant.session.board.slave if plant.session.board else ""},
                      record_dir, gains=plant.gains, virtual=plant, keepalive=False)
            plant.start(hub)
        else:
            port = args.port
            mode = "board"
            if args.emulate:
                print("upright dashboard: booting the emulated RP2040...", file=sys.stderr, flush=True)
                emu, port = _start_emulator()
                mode = "emulated rp2040"
            try:
                link = open_link(port, node_id=args.node, baudrate=args.baudrate)
            except LinkError as exc:
                raise A.RunFailed(str(exc)) from None
            hub = Hub(link, {"mode": mode, "port": port}, record_dir, keepalive=True)
            pump = PlainPump(hub).start()
            try:
                hub.link.query("heartbeat", timeout=3.0 if args.emulate else 0.5, retries=2)
            except LinkError as exc:
                raise A.RunFailed(f"the board on {port} does not answer: {exc}") from None
        try:
            server = DashboardServer(hub, "127.0.0.1", args.http_port).start()
        except OSError as exc:
            raise A.RunFailed(f"--http-port {args.http_port}: {exc.strerror or exc}") from None
        print(server.page_url, flush=True)
        print(f"upright dashboard: open {server.page_url} (Ctrl-C stops; the board is disarmed on exit)",
              file=sys.stderr, flush=True)
        t_end = None if args.seconds is None else time.monotonic() + args.seconds
        while t_end is None or time.monotonic() < t_end:
            time.sleep(0.1)
            err = (plant.error if plant is not None else None) or (pump.error if pump is not None else None)
            if err:
                raise A.RunFailed(err)
        return 0
    finally:
        _shutdown(hub, server, plant, pump, link, emu)


def _shutdown(hub: Any, server: Any, plant: Any, pump: Any, link: Any, emu: Any) -> None:
    # disarm what can still be reached (first, and with every further signal ignored), then stop
    # everything, each step on its own
    held = _install(_note_signal, (signal.SIGINT, *SHUTDOWN_SIGNALS))
    try:
        if hub is not None:
            _disarm(hub, plant)
            hub.close()
        if server is not None:
            server.stop()
        if pump is not None:
            pump.stop()
        if plant is not None:
            plant.stop()
        if link is not None:
            from host.link.clients import LinkError

            try:
                link.close()
            except (LinkError, OSError):
                pass
        if emu is not None:
            try:
                emu.terminate()  # SIGTERM: upright emulate stops and removes its files
                emu.wait(timeout=15.0)
            except (OSError, subprocess.TimeoutExpired):
                emu.kill()
                emu.wait()
    finally:
        _restore(held)


def _note_signal(signum: int, frame: object) -> None:
    # during the shutdown: the disarm must not be cut short (it takes at most a few seconds)
    print(f"upright dashboard: {signal.Signals(signum).name} while disarming: ignored", file=sys.stderr, flush=True)


def _disarm(hub: Any, plant: Any) -> None:
    """Disarm the board, then wait for its own word: the heartbeat (and, on the virtual board, the
    firmware's per-tick answer) saying disarmed; one line on stderr either way."""
    from firmware import msgtable as T
    from host.link.clients import LinkError
    from host.operate.board import BoardError

    armed = {s[0] for s in T.STATES if s[1] in ("armed", "balancing")}
    t0 = time.monotonic()
    try:
        hub.disarm_now()
    except (LinkError, OSError, BoardError) as exc:
        print(f"upright dashboard: disarm failed: {' '.join(str(exc).split())} "
              "(the board's link watchdog cuts the motor without a host heartbeat)", file=sys.stderr, flush=True)
        return
    from host.dashboard.hub import COLUMNS

    i_state = COLUMNS.index("state")
    t_end = time.monotonic() + _CONFIRM_S
    state = None
    while time.monotonic() < t_end:
        hb = hub.heartbeat or {}
        state = hb.get("state")
        fw = plant.fw_state if plant is not None else None
        # the last telemetry row shows the disarmed state too, so a recording ends with it
        last = hub.rows[-1][i_state] if hub.rows else None
        if state is not None and state not in armed and (fw is None or fw not in armed) and last not in armed:
            break
        time.sleep(0.02)
    from host.link import messages as M

    name = M.STATES.get(state, "unknown") if state is not None else "no heartbeat"
    if state is not None and state not in armed:
        ms = (time.monotonic() - t0) * 1000.0
        print(f"upright dashboard: board disarmed in {ms:.0f} ms (its heartbeat: {name})", file=sys.stderr, flush=True)
    else:
        print(f"upright dashboard: disarm sent, not confirmed within {_CONFIRM_S:g} s (last heartbeat: {name})",
              file=sys.stderr, flush=True)
