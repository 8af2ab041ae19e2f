"""``upright emulate rp2040 --pty | --can``: the virtual robot -- an emulated Pico running the
firmware with the simulated robot on its pins -- its host link on a pty or on a CAN bus.

Starts the firmware bundle on the emulated RP2040 (rp2040js, MicroPython's rp2 port: the board
as after ``make flash``), closes the simulated robot around its pins (``--plant FILE``, default
``sim/robot.toml``: :mod:`host.hil.virtual_robot` -- the plant of ``hil --emulate``, stepped
with the board's own emulated clock), bridges its host link (UART0, 1 Mbaud) to a new
pseudo-terminal and its USB CDC port (the Pico's micro-USB: MicroPython's REPL) to a second one,
and prints the two paths on stdout, the host link's first.  Every tool that takes ``--port``
then works against it as against a robot on ``/dev/ttyUSB0``::

    $ upright emulate rp2040 --pty
    /dev/pts/7
    /dev/pts/8
    $ upright board --port /dev/pts/7 calibrate --out robot.toml   # in another terminal

With ``--link usb`` the board runs its host link on the USB CDC port instead (``LINK = "usb"``
in ``firmware/board.py``; the bundle is unchanged, its ``main.py`` calls
``main.main(link="usb")``): the first path is then the USB one, as ``/dev/ttyACM0``, and
``upright board --port /dev/pts/7 mode repl`` hands it back to the REPL.

The pendulum starts upright at rest, held by the robot's stand-by person until the board
balances (then let go), and caught again when the motor goes off (a disarm, a fault).  What else a
person does to a robot (hold it upright or tilted, roll the cart, lift the wheels, take the
pendulum off, press reset) is asked for on the robot's hands, a Unix socket whose path is
derived from the port (:func:`host.hil.hands.hands_path`; printed at start): ``upright
board calibrate`` finds it there by itself (``--robot auto``), and a real robot has none.

With ``--can [CHANNEL]`` the board runs its CAN link instead (``main.main(link="can")``: the
MCP2515 on SPI1, modelled at the register level) and the emulated bus is bridged to a python-can
bus (``--can-interface``, default ``udp_multicast``: every process on the machine that opens the
same group joins it; the default group is interface-local, so no frame leaves the machine).  It
prints the bus as one ``can:INTERFACE:CHANNEL`` line (what ``upright proto dump`` takes)::

    $ upright emulate rp2040 --can
    can:udp_multicast:ff11:7079:7468:6f6e:6465:6d6f:6d63:6173
    $ upright board --link can --can-interface udp_multicast --port ff11:7079:7468:6f6e:6465:6d6f:6d63:6173 status

It serves until Ctrl-C (exit status 130, "interrupted", as every command) or SIGTERM / SIGHUP
(exit status 0), whatever its standard input is (never read: ``nohup``, ``< /dev/null`` and
``&`` serve the same), and leaves nothing behind (the board's node process, its temporary
directory and the hands' socket are removed).  The emulation runs at about 0.1-0.4x real time:
board time passes slower than on the wall, and the robot with it.  A board that does not boot
or whose firmware raises ends the command with exit status 1 and its last output.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any, Sequence

__all__ = ["add_arguments", "run", "hil_emulated"]

_SIGINT = 2
UDP_LOCAL_GROUP = "ff11:7079:7468:6f6e:6465:6d6f:6d63:6173"
"""Default ``udp_multicast`` group (= ``host.boards.rp2040.can.UDP_LOCAL_GROUP``, not imported at
start-up): interface-local IPv6 scope, delivered on this machine only."""
SOCKETCAN_DEFAULT = "vcan0"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright emulate``."""
    from host.cli.args import can_interface

    parser.add_argument("board", choices=("rp2040",), help="the emulated board (rp2040: Raspberry Pi Pico)")
    link = parser.add_mutually_exclusive_group(required=True)
    link.add_argument("--pty", action="store_true",
                      help="bridge the board's host link (UART0) to a new pseudo-terminal and print its path")
    link.add_argument("--can", nargs="?", const="", default=None, metavar="CHANNEL",
                      help="run the board's CAN link (MCP2515 on SPI1) and bridge its bus to the python-can "
                           f"channel CHANNEL (default for udp_multicast: {UDP_LOCAL_GROUP}, loopback only; "
                           f"socketcan: {SOCKETCAN_DEFAULT}); prints can:INTERFACE:CHANNEL")
    parser.add_argument("--can-interface", type=can_interface, default="udp_multicast", metavar="NAME",
                        help="python-can interface of --can: udp_multicast (default; other processes on this "
                             "machine), socketcan (a vcan/can interface), ... -- not virtual (one process only)")
    parser.add_argument("--link", choices=("uart", "usb"), default=None,
                        help="--pty: the board's host link, UART0 (default: firmware/board.py LINK) or its USB CDC "
                             "port (LINK = \"usb\": the link on the Pico's micro-USB, /dev/ttyACM0 on a real one)")
    parser.add_argument("--plant", metavar="TOML", default=None,
                        help="the simulated robot on the board's pins: a robot TOML or a name from sim/plants/ "
                             "(default sim/robot.toml, the design the firmware ships for)")
    parser.add_argument("--bundle", metavar="DIR", default=None,
                        help="firmware bundle to put on the board's flash (default: built from firmware/)")


class _Stop:
    """Ctrl-C (SIGINT), SIGTERM and SIGHUP (the terminal went away) end the serve loop cleanly:
    the board's node process and temporary files are removed, the robot's socket too.  Standard
    input is never read, so the command serves the same under ``nohup``, ``< /dev/null`` or ``&``."""

    SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP")

    def __init__(self) -> None:
        self.signum = 0
        self._old: dict[int, Any] = {}

    def __enter__(self) -> "_Stop":
        import signal

        for name in self.SIGNALS:
            sig = getattr(signal, name)
            try:
                old = signal.getsignal(sig)
                if sig == signal.SIGHUP and old == signal.SIG_IGN:
                    continue  # nohup: keep ignoring it
                self._old[sig] = old
                signal.signal(sig, self._on)
            except (ValueError, OSError):  # pragma: no cover - not the main thread
                pass
        return self

    def _on(self, signum: int, frame: object) -> None:
        self.signum = signum

    def __call__(self) -> bool:
        return bool(self.signum)

    def __exit__(self, *exc: object) -> None:
        import signal

        for sig, old in self._old.items():
            try:
                signal.signal(sig, old)
            except (ValueError, OSError):  # pragma: no cover
                pass

    def stopped(self) -> bool:
        """A stop signal came (or comes within a moment: a Ctrl-C on the terminal reaches the
        board's node process too, which may end first)."""
        if not self.signum:
            time.sleep(0.3)
        return bool(self.signum)


def _how_to_stop() -> str:
    return f"Ctrl-C or SIGTERM (kill {os.getpid()}) stops it"


def _robot(args: argparse.Namespace) -> Any:
    """The simulated robot: ``--plant`` or the design (``sim/robot.toml``)."""
    from host.cli.plant import load_plant
    from host.hil.virtual_robot import VirtualRobot
    from sim.params import load_params

    design = load_params()
    plant = load_plant(args.plant, design) or design
    return VirtualRobot(plant)


def _serve(link: Any, robot: Any, port_key: str, stop: _Stop) -> int:
    # the robot on the pins, its hands on a socket next to the port's name, until a stop signal
    from host.boards.rp2040.board import BoardError
    from host.hil.hands import HandsServer, hands_path
    from host.hil.virtual_robot import serve

    robot.port = port_key
    hands = HandsServer(hands_path(port_key), robot)
    try:
        print(f"upright emulate: the simulated robot ({robot.params.source}) on the board's pins, the pendulum "
              f"held upright until the board balances; its hands (calibrate --robot auto, tests) on {hands.path}",
              file=sys.stderr, flush=True)
        try:
            serve(link, robot, stop, hands)
        except BoardError as exc:
            if not stop.stopped():
                return _board_failed(exc)
    finally:
        hands.close()
    if stop.signum != _SIGINT:
        print("upright emulate: stopped", file=sys.stderr, flush=True)
    return 0


def run(args: argparse.Namespace) -> int:
    """Run ``upright emulate``."""
    import signal

    from host.cli.args import UsageError

    bundle = None
    if args.bundle is not None:
        bundle = Path(args.bundle)
        if not (bundle / "main.py").is_file():
            raise UsageError(f"--bundle: {bundle} holds no main.py (make firmware writes one)")
    robot = _robot(args)
    with _Stop() as stop:
        if args.can is not None and args.link is not None:
            raise UsageError("--link: with --can the board's host link is its CAN bus (MCP2515 on SPI1)")
        status = (_serve_can(args, bundle, robot, stop) if args.can is not None
                  else _serve_pty(bundle, robot, stop, args.link or _board_link()))
    if stop.signum == signal.SIGINT:
        raise KeyboardInterrupt  # Ctrl-C: "interrupted", exit status 130 as every command (SIGTERM: 0)
    return status


def _board_link() -> str:
    # firmware/board.py LINK, as the board reads it ("uart0" is "uart"; "can" has its own flag)
    from firmware import board as fb

    link = str(getattr(fb, "LINK", "uart"))
    return "usb" if link == "usb" else "uart"


def _serve_pty(bundle: Path | None, robot: Any, stop: _Stop, link: str = "uart") -> int:
    """``--pty``: the board's UART0 and USB CDC port each on a new pty, the robot on its pins,
    until a stop signal; stdout: the host link's pty, then the other one."""
    from host.boards.rp2040.board import BoardError
    from host.boards.rp2040.bridge import PtyBridge

    where = "the host link on USB: main.main(link='usb')" if link == "usb" else "main.py"
    print(f"upright emulate: booting the emulated RP2040 ({where})...", file=sys.stderr, flush=True)
    try:
        bridge = PtyBridge(bundle, adc=robot.plant.read()[0], link=link)
    except BoardError as exc:
        return 0 if stop.stopped() else _board_failed(exc)
    try:
        if stop():
            return 0
        other = bridge.uart_port if link == "usb" else bridge.usb_port
        print(f"{bridge.port}\n{other}", flush=True)
        if link == "usb":
            ports = (f"host link (USB CDC, the Pico's micro-USB) on {bridge.port}, `upright board --port "
                     f"{bridge.port} mode repl` hands it to MicroPython's REPL; UART0 (unused) on {other}")
        else:
            ports = (f"host link (UART0, {bridge.board.uart_baud} baud) on {bridge.port}; the USB CDC port "
                     f"(MicroPython's REPL, as /dev/ttyACM0: mpremote connect {other}) on {other}")
        print(f"upright emulate: {ports}; {_how_to_stop()}", file=sys.stderr, flush=True)
        return _serve(bridge, robot, bridge.port, stop)
    finally:
        bridge.close()


def _can_channel(interface: str, channel: str) -> str:
    """The channel of ``--can`` (its default per interface); refuses what cannot work (exit 2)."""
    import ipaddress

    from host.cli.args import UsageError

    if interface == "virtual":
        raise UsageError("--can-interface virtual: python-can's virtual bus lives inside one process, no other "
                         "tool could join it; use udp_multicast (this machine) or socketcan (vcan0)")
    if not channel:
        channel = {"udp_multicast": UDP_LOCAL_GROUP, "socketcan": SOCKETCAN_DEFAULT}.get(interface, "")
        if not channel:
            raise UsageError(f"--can: name the {interface} channel (e.g. --can PCAN_USBBUS1)")
    if interface == "udp_multicast":
        try:
            addr = ipaddress.ip_address(channel)
        except ValueError:
            raise UsageError(f"--can: a udp_multicast channel is a multicast group address, got {channel!r} "
                             f"(default {UDP_LOCAL_GROUP})") from None
        if not addr.is_multicast:
            raise UsageError(f"--can: {channel} is not a multicast group address (default {UDP_LOCAL_GROUP})")
        if not (addr.version == 6 and (addr.packed[1] & 0x0F) == 1):
            print(f"upright emulate: note: group {channel} is not interface-local (ff?1::); the bus's frames "
                  "also go out on the network", file=sys.stderr)
    return channel


def _serve_can(args: argparse.Namespace, bundle: Path | None, robot: Any, stop: _Stop) -> int:
    """``--can``: the board's CAN link bridged to a python-can bus, the robot on its pins, until a
    stop signal."""
    from host.boards.rp2040.board import BoardError
    from host.boards.rp2040.can import CanBoard

    interface = args.can_interface
    channel = _can_channel(interface, args.can)
    print(f"upright emulate: booting the emulated RP2040 (main.py, CAN link) on python-can {interface} "
          f"{channel}...", file=sys.stderr, flush=True)
    try:
        board = CanBoard(channel=channel, interface=interface, bundle_dir=bundle,
                         adc=robot.plant.read()[0])
    except BoardError as exc:
        if stop.stopped():
            return 0
        return _board_failed(exc)
    except Exception as exc:  # python-can could not open the bus (no such interface, no vcan0, ...)
        if type(exc).__module__.split(".")[0] != "can" and not isinstance(exc, (OSError, ImportError)):
            raise
        print(f"upright emulate: cannot open python-can {interface} channel {channel}: "
              f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}", file=sys.stderr)
        return 1
    try:
        from firmware import board as fb

        print(f"can:{interface}:{channel}", flush=True)
        print(f"upright emulate: host link (CAN, MCP2515 on SPI1, {fb.CAN_BITRATE // 1000} kbit/s, node 1) on "
              f"python-can {interface} {channel}; {_how_to_stop()}\n"
              f"upright emulate: e.g. upright board --link can --can-interface {interface} --port {channel} status",
              file=sys.stderr, flush=True)
        return _serve(board, robot, f"can:{interface}:{channel}", stop)
    finally:
        board.close()


def _board_failed(exc: BaseException, who: str = "upright emulate") -> int:
    """One line naming the failure, then the board's last output (exit status 1)."""
    head, _, tail = str(exc).partition("\n")
    print(f"{who}: {head}", file=sys.stderr)
    if tail:
        print(tail, file=sys.stderr)
    return 1


def hil_emulated(args: argparse.Namespace, out: Path, scenarios: Sequence[Any], progress: Any,
                 json_path: Path | None, *, cli: Any, plant: Any = None) -> int:
    """``upright hil --emulate rp2040``: the scenarios on the emulated Pico, the plant on its pins.

    Same table, CSV/PNG/GIF and summary file as ``--virtual`` (:mod:`host.cli.hil`), plus the
    loop's tick time in emulated cycles; ``--json`` writes :func:`host.hil.records.scenario_record`
    per scenario.  A board that fails prints one line and its last output (exit status 1);
    Ctrl-C writes what finished, marked partial.  ``cli`` is :mod:`host.cli.hil` (its table,
    summary file and partial-run helpers; passed in, so the two modules import no circle).
    ``plant`` (``--plant``): the robot on the board's pins when it differs from the design (the
    firmware keeps its gains; a scenario's ``[params]`` apply on top, as for ``--virtual``).
    """
    from host.boards.rp2040.board import BoardError
    from host.cli.main import interrupted
    from host.hil.emulated import run_emulated
    from host.hil.errors import HilError
    from host.hil.records import write_records

    if args.link == "can":
        # the board's CAN link: its MCP2515 on SPI1 bridged to python-can (host/hil/emulated_can.py)
        from host.hil.emulated_can import run_emulated_can as run_emulated  # noqa: F811
    if not args.quiet:
        link = "CAN link: MCP2515 on SPI1, python-can virtual bus" if args.link == "can" else "UART0 link"
        print(f"upright hil: {len(scenarios)} scenario(s), emulated RP2040 (main.py, {link}, plant on the pins; "
              "about 0.1-0.2 board seconds per wall second)", file=sys.stderr)
    done: list[Any] = []
    try:
        runs = run_emulated(scenarios, out=out, compare=not args.no_compare, gif=not (args.no_gif or args.no_plots),
                            plot=not args.no_plots, progress=progress, on_result=done.append, plant=plant)
    except (BoardError, HilError) as exc:
        if not interrupted():
            return _board_failed(exc, "upright hil")
        cli._partial(done, out, scenarios, args.tolerance)
        raise KeyboardInterrupt from None
    except KeyboardInterrupt:
        cli._partial(done, out, scenarios, args.tolerance)
        raise
    cli.write_summary(runs, out, planned=scenarios, tolerance=args.tolerance)
    if json_path is not None:
        write_records(runs, json_path)
    status = cli.report(runs, tolerance=args.tolerance, out=out)
    for r in runs:
        st = r.stats
        print(f"  {r.name:28s} loop tick {st['tick_us_mean']:.0f} us mean, {st['tick_us_max']:.0f} us max "
              f"of {st['period_us']:.0f} us ({100 * st['tick_us_max'] / st['period_us']:.0f} %), "
              f"{st['overruns']} overrun(s); emulator {st['emu_speed']:.2f} board s per wall s", file=sys.stdout)
    return status
