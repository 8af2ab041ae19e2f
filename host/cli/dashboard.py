"""``upright dashboard``: a live web page for a board -- plots, state, arm/disarm, reference, gains, recording.

::

    upright dashboard --virtual                    # the firmware on a pty, balancing the simulated robot
    upright dashboard --port /dev/ttyUSB0          # a board (its link at the board's UART rate)
    upright dashboard --emulate rp2040             # the emulated Pico (``upright emulate rp2040 --pty``)

Prints the page's address (``http://127.0.0.1:8765/``) on stdout, one line, and serves until
Ctrl-C (or ``--seconds``).  Everything the page loads is served from the project (uPlot from
``node_modules``).  The dashboard keeps the board's watchdog fed only while a page is open and
the arm was asked from it; when the last page closes it stops and disarms the board; on exit it
disarms the board it can still reach.  Recordings go to ``--record-dir`` (CSV, one row per
telemetry frame) and download from the page.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from host.cli import args as A

__all__ = ["add_arguments", "run"]


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
    parser.add_argument("--baudrate", type=A.positive_int, default=A.board_baud(),
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
    """Run ``upright dashboard``."""
    from host.dashboard.hub import Hub, PlainPump, SharedLink
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
            shared = plant.open()
            hub = Hub(shared, {"mode": "virtual", "port": plant.session.board.slave if plant.session.board else ""},
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
            shared = SharedLink(link)
            hub = Hub(shared, {"mode": mode, "port": port}, record_dir, keepalive=True)
            pump = PlainPump(hub).start()
            try:
                hub.cmd.query("heartbeat", timeout=3.0 if args.emulate else 0.5, retries=2)
            except LinkError as exc:
                raise A.RunFailed(f"the board on {port} does not answer: {exc}") from None
        try:
            server = DashboardServer(hub, "127.0.0.1", args.http_port).start()
        except OSError as exc:
            raise A.RunFailed(f"--http-port {args.http_port}: {exc.strerror or exc}") from None
        print(server.url, flush=True)
        print(f"upright dashboard: open {server.url} (Ctrl-C stops; the board is disarmed on exit)",
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
    # disarm what can still be reached, then stop everything, each step on its own
    from host.link.clients import LinkError
    from host.operate.board import BoardError

    if hub is not None:
        try:
            hub.disarm_now()
        except (LinkError, OSError, BoardError):
            pass
        hub.close()
    if server is not None:
        server.stop()
    if pump is not None:
        pump.stop()
    if plant is not None:
        plant.stop()
    if link is not None:
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
