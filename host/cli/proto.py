"""``upright proto``: encode / decode protocol messages as hex, list them, dump a live link.

Examples::

    upright proto list
    upright proto encode set_reference x_um=0.25 --physical        # serial frame, hex
    upright proto encode param_get index=3 --can --node 1          # candump style 021#03
    upright proto decode 000b0b0203...00                           # serial bytes (any number of frames)
    upright proto decode 02C#03 --can                              # CAN id#data
    upright proto dbc --node 3 > node3.dbc                           # CAN database for another node
    upright proto dump                    # the board on /dev/ttyUSB0 at its UART rate (1 Mbaud)
    upright proto dump loop://            # or /dev/ttyACM0, can:socketcan:can0, can:serial:/dev/pts/3
    upright proto dump --port /dev/pts/3  # --port as every other tool (positional kept)
"""

from __future__ import annotations

import argparse
import sys
import time

from host.cli import args as A
from host.link import messages as M

DEFAULT_DUMP_PORT = "/dev/ttyUSB0"
"""``upright proto dump``'s default link: the USB-serial adapter on the board's UART0 (GP0/GP1)."""

__all__ = ["add_arguments", "run", "parse_fields", "format_can", "parse_can"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``upright proto``."""
    sub = parser.add_subparsers(dest="proto_cmd", metavar="ACTION")
    sub.required = True
    sp = sub.add_parser("list", help="list the messages, reasons and parameters of the table")
    sp.set_defaults(_proto=_cmd_list)

    sp = sub.add_parser("encode", help="encode one message to hex")
    sp.add_argument("name", help="message name (see `upright proto list`)")
    sp.add_argument("fields", nargs="*", metavar="FIELD=VALUE", help="field values (raw ints; bytes as hex)")
    sp.add_argument("--physical", action="store_true", help="values are physical units (scaled by the table)")
    sp.add_argument("--seq", type=A.int_range(0, 255), default=0, help="serial sequence number (default 0)")
    _framing(sp)
    sp.set_defaults(_proto=_cmd_encode)

    sp = sub.add_parser("decode", help="decode hex bytes (serial stream) or ID#DATA (CAN)")
    sp.add_argument("hex", nargs="+", help="hex bytes (spaces and ':' allowed), or ID#DATA with --can")
    _framing(sp)
    sp.set_defaults(_proto=_cmd_decode)

    sp = sub.add_parser("dbc", help="print the CAN database (DBC) for a node id")
    sp.add_argument("--node", type=int, default=None, help="CAN node id (default: the node_id parameter default)")
    sp.set_defaults(_proto=_cmd_dbc)

    sp = sub.add_parser("dump", help="print every message received on a live link (like candump)")
    sp.add_argument("link", nargs="?", default=DEFAULT_DUMP_PORT, type=A.nonempty, metavar="PORT",
                    help=f"serial port/URL (loop://, /dev/ttyACM0) or can:INTERFACE:CHANNEL (default {DEFAULT_DUMP_PORT}); "
                         "the same as --port")
    sp.add_argument("--port", dest="port_opt", default=None, type=A.nonempty, metavar="PORT",
                    help="the link, as every other tool takes it (or give it positionally)")
    sp.add_argument("--node", type=A.int_range(0, 63), default=1, help="CAN node id (default 1)")
    sp.add_argument("--baudrate", "--baud", dest="baudrate", type=A.positive_int, default=A.board_baud(),
                    help=f"serial baud rate (default {A.board_baud()}: firmware/board.py UART_BAUD)")
    sp.add_argument("--count", type=A.nonneg_int, default=0, help="stop after this many messages (0 = no limit)")
    sp.add_argument("--duration", type=A.in_range(0.0, 7 * 24 * 3600.0, unit="s"), default=0.0,
                    help="stop after this many seconds (0 = no limit)")
    sp.set_defaults(_proto=_cmd_dump)


def _framing(sp: argparse.ArgumentParser) -> None:
    sp.add_argument("--can", action="store_true", help="CAN framing (default: serial COBS framing)")
    sp.add_argument("--node", type=A.int_range(0, 63), default=1, help="CAN node id (default 1)")


def run(args: argparse.Namespace) -> int:
    """Run ``upright proto ACTION``."""
    return int(args._proto(args) or 0)


# ---------------------------------------------------------------- helpers
def parse_fields(cls: type[M.Message], items: list[str], physical: bool = False) -> M.Message:
    """Build a message from ``FIELD=VALUE`` strings.

    Raises
    ------
    ValueError
        Malformed item, unknown or missing field, or a value out of range.
    """
    values: dict[str, object] = {}
    fields = {f.name: f for f in cls.FIELDS}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep:
            raise ValueError(f"expected FIELD=VALUE, got {item!r}")
        f = fields.get(key)
        if f is None:
            raise ValueError(f"{cls.NAME} has no field {key!r}; fields: {', '.join(fields) or 'none'}")
        if f.is_raw:
            try:
                values[key] = bytes.fromhex(text)
            except ValueError:
                raise ValueError(f"{cls.NAME}.{key}: expected hex bytes, got {text!r}") from None
        elif physical:
            values[key] = float(text)
        else:
            try:
                values[key] = int(text, 0)
            except ValueError:
                raise ValueError(f"{cls.NAME}.{key}: expected an integer raw value, got {text!r} (use --physical for units)") from None
    # the integrity check of a command that moves the cart is computed when not given
    missing = [n for n in fields if n not in values and n != cls.AUTO_CHECK]
    if missing:
        raise ValueError(f"{cls.NAME}: missing field(s) {', '.join(missing)}")
    if physical:
        return cls.from_physical(**values)
    return cls(**values)


def format_can(arbitration_id: int, data: bytes) -> str:
    """candump/cansend style ``III#DDDD`` text."""
    return f"{arbitration_id:03X}#{bytes(data).hex().upper()}"


def parse_can(text: str) -> tuple[int, bytes]:
    """Parse ``III#DDDD``.

    Raises
    ------
    ValueError
    """
    ident, sep, data = text.partition("#")
    if not sep:
        raise ValueError(f"CAN frame must be ID#DATA (hex), got {text!r}")
    try:
        return int(ident, 16), bytes.fromhex(data.replace(".", ""))
    except ValueError:
        raise ValueError(f"CAN frame must be ID#DATA (hex), got {text!r}") from None


def _hex(parts: list[str]) -> bytes:
    text = "".join(parts).replace(":", "").replace(" ", "")
    try:
        return bytes.fromhex(text)
    except ValueError:
        raise ValueError(f"not hex bytes: {text!r}") from None


# ---------------------------------------------------------------- actions
def _cmd_list(args: argparse.Namespace) -> int:
    print("messages (id  name  direction  payload bytes: fields):")
    for cls in M.MESSAGES.values():
        fields = ", ".join(f"{f.name}:{f.fmt}" + (f"[{f.unit}]" if f.unit else "") for f in cls.FIELDS)
        print(f"  {cls.ID:2d}  {cls.NAME:<14} {cls.DIRECTION:<8} {cls.STRUCT.size}: {fields}")
    print("refusal reasons:")
    for code, (name, doc) in M.REASONS.items():
        print(f"  {code:2d}  {name:<14} {doc}")
    print("parameters (index name unit min..max default):")
    for name, (i, unit, lo, hi, d, _) in M.PARAMS.items():
        print(f"  {i:2d}  {name:<16} {unit:<6} {lo}..{hi}  default {d}")
    return 0


def _cmd_encode(args: argparse.Namespace) -> int:
    msg = parse_fields(M.message_class(args.name), args.fields, args.physical)
    if args.can:
        print(format_can(*M.encode_can(msg, args.node)))
    else:
        if not 0 <= args.seq <= 255:
            raise ValueError(f"--seq must be 0..255, got {args.seq}")
        print(M.encode_serial(msg, args.seq).hex())
    return 0


def _cmd_decode(args: argparse.Namespace) -> int:
    if args.can:
        for text in args.hex:
            node, msg = M.decode_can(*parse_can(text))
            print(f"node {node}  {msg}")
        return 0
    data = _hex(args.hex)
    if not data.strip(b"\x00"):
        what = "no bytes" if not data else f"only frame delimiters ({data.hex()})"
        raise ValueError(f"nothing to decode: the input holds {what}, no frame; give a frame's bytes in hex "
                         f"(e.g. from `upright proto encode`)")
    dec = M.SerialStreamDecoder()
    frames = dec.feed(data + b"\x00")
    for msg, seq in frames:
        print(f"seq {seq:3d}  {msg}")
    dropped = {k: v for k, v in dec.drops.items() if v}
    if dropped:
        print("dropped: " + ", ".join(f"{k}={v}" for k, v in dropped.items()), file=sys.stderr)
    return 0 if frames and not dropped else 1


def _cmd_dbc(args: argparse.Namespace) -> int:
    from host.link.dbc import render_dbc

    if args.node is not None and not 0 <= args.node < 64:
        raise A.UsageError(f"--node must be 0..63, got {args.node}")
    sys.stdout.write(render_dbc(args.node))
    return 0


def _dump_port(args: argparse.Namespace) -> str:
    # (the positional's default is the default port: a positional that differs from it and
    # from --port is a second port)
    pos, opt = args.link, args.port_opt
    if opt is not None and pos not in (DEFAULT_DUMP_PORT, opt):
        raise A.UsageError(f"proto dump: two ports, {pos!r} and --port {opt!r}: give one")
    return opt or pos


def _cmd_dump(args: argparse.Namespace) -> int:
    from host.link.clients import open_link

    args.link = _dump_port(args)
    n = 0
    t0 = time.monotonic()
    with open_link(args.link, node_id=args.node, baudrate=args.baudrate) as link:
        try:
            while True:
                left = None
                if args.duration:
                    left = args.duration - (time.monotonic() - t0)
                    if left <= 0:
                        break
                msg = link.recv(timeout=0.2 if left is None else min(0.2, left))
                if msg is None:
                    continue
                n += 1
                seq = f" seq {link.last_seq:3d}" if getattr(link, "last_seq", None) is not None else ""
                print(f"({time.monotonic() - t0:10.4f}) {args.link}{seq}  {msg}", flush=True)
                if args.count and n >= args.count:
                    break
        except KeyboardInterrupt:
            pass
        drops = {k: v for k, v in link.drops.items() if v}
    if drops:
        print("dropped: " + ", ".join(f"{k}={v}" for k, v in drops.items()), file=sys.stderr)
    return 0
