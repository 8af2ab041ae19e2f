"""``upright commission --port DEV [--out DIR] [--resume] [--until STAGE]``: first power-up to a verified robot.

The stages (identity and sensor checks, calibration, cart-only run, first design and upload,
balancing run with a growing excitation, identification, the design with margin, verification of
the report's 20 cm step and 0.2 N push on the robot, save) are those of
:mod:`host.operate.commission`; each one done is recorded in ``DIR/commission.json`` and
``--resume`` goes on after the last (``--until STAGE`` stops after STAGE: one stage per
command).  ``--virtual --plant FILE`` commissions a simulated robot instead: the firmware under
the MicroPython unix port in lockstep HIL with the robot file's plant
(:mod:`host.operate.commission_lockstep`).  On a board every wait and run follows the board's
own clock (measured when it answers): the virtual robot of ``upright emulate rp2040 --pty``,
slower than real time, commissions like a real robot, only later.  Examples::

    upright commission --port /dev/ttyUSB0 --out out/commission
    upright commission --port /dev/ttyUSB0 --out out/commission --until calibrate   # then --resume
    upright commission --virtual --plant realistic_cart --out out/commission_sim

Exit status: 0 commissioned and verified; 1 a stage refused or the verification failed (the
state file says where; ``--resume`` after fixing); 2 bad options.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from host.cli import args as A


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright commission``."""
    parser.add_argument("--port", metavar="DEV", help="the board's serial port (a real robot or the virtual robot's pty)")
    parser.add_argument("--baudrate", type=A.positive_int, default=A.board_baud(),
                        help=f"serial line rate (default {A.board_baud()})")
    parser.add_argument("--timeout", type=A.in_range(0.05, 60), default=None, metavar="S",
                        help="--port: seconds per request attempt (3 retries; default 0.3 scaled by the board's "
                             "measured clock, as every board tool)")
    parser.add_argument("--virtual", action="store_true",
                        help="no board: the firmware on the unix port in lockstep HIL with --plant's robot")
    parser.add_argument("--plant", default=None, metavar="TOML",
                        help="with --virtual: the simulated robot (a path or a name in sim/plants/)")
    parser.add_argument("--params", default=None, metavar="TOML",
                        help="the robot file to start from: weighed masses, drive, sensors (default sim/robot.toml)")
    parser.add_argument("--out", default="out/commission", metavar="DIR",
                        help="logs, robot files, state and report.html (default out/commission)")
    parser.add_argument("--resume", action="store_true", help="go on after the last stage recorded in DIR")
    parser.add_argument("--robot", default="auto", metavar="auto|person|SOCKET",
                        help="who does the hands' steps: the virtual robot's hands (auto, the default, when "
                             "one listens on the port) or a person prompted on the terminal")
    parser.add_argument("--until", default=None, metavar="STAGE",
                        help="stop after STAGE (identity ... save, in order; a wrong name lists them); --resume "
                             "goes on from there: one stage per command")
    parser.add_argument("--fast", action="store_true", help="shorter runs and fewer design candidates")
    parser.add_argument("--seed", type=A.int_range(0, 2**31 - 1), default=0, help="--virtual: plant noise seed")


def run(args: argparse.Namespace) -> int:
    """Run ``upright commission``."""
    from host.operate.commission import STAGES, STATE_FILE, Commission, CommissionError
    from host.operate.board import BoardError
    from sim.params import load_params

    if args.until is not None and args.until not in STAGES:
        raise A.UsageError(f"--until: unknown stage {args.until!r}; the stages: {', '.join(STAGES)}")
    if bool(args.port) == bool(args.virtual):
        raise A.UsageError("give --port DEV (a board) or --virtual --plant FILE (lockstep HIL), not both or neither")
    if args.plant and not args.virtual:
        raise A.UsageError("--plant goes with --virtual (a board is the robot itself)")
    out = Path(args.out)
    if (out / STATE_FILE).exists() and not args.resume:
        raise A.UsageError(f"--out {out} already holds a commissioning ({STATE_FILE}): --resume to go on, "
                           "or another --out")
    if args.resume and not (out / STATE_FILE).exists():
        raise A.UsageError(f"--resume: no {STATE_FILE} in {out}")
    load_params(args.params)  # a bad robot file: one line before anything moves

    def say(text: str) -> None:
        print(text, flush=True)

    if args.virtual:
        from host.cli.plant import load_plant
        from host.operate.commission_lockstep import LockstepRobot

        design = load_params(args.params)
        robot = LockstepRobot(load_plant(args.plant, design) or design, seed=args.seed)
    else:
        from host.operate.commission_port import PortRobot

        robot = PortRobot(args.port, baudrate=args.baudrate, hands=args.robot, timeout=args.timeout, say=say)
    try:
        with robot:
            c = Commission(robot, out, params_in=args.params, say=say, fast=args.fast)
            if args.resume:
                c.load()
            stages = STAGES[:STAGES.index(args.until) + 1] if args.until else STAGES
            data = c.run(stages)
    except (CommissionError, BoardError) as exc:
        print(f"upright commission: {exc} (state in {out / STATE_FILE}; --resume after fixing)", file=sys.stderr)
        return A.EXIT_FAILED
    if "save" not in c.state["done"]:
        print(f"stopped after {stages[-1]} (--until): done {', '.join(c.state['done'])}; --resume goes on "
              f"(state in {out / STATE_FILE})")
        return 0
    ver = data.get("verify", {})
    ok = all(v.get("pass", True) for v in ver.values())
    print(f"commissioned: {out / 'robot.toml'}, report {out / 'report.html'}; verification "
          f"{'PASS' if ok else 'FAIL'}")
    return 0 if ok else A.EXIT_FAILED
