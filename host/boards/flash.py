"""``make flash``: copy the firmware bundle to a board with mpremote -- after checking, within a
few seconds, that the port is a MicroPython REPL.

mpremote on a port that is not a board's REPL (a USB-serial adapter, a board whose USB runs
the upright link, nothing at all) waits for minutes and prints nothing.  This wrapper says
what it waits for, and gives up in one line naming the cause:

1. the port exists and no other process holds it (the one-line ``port busy`` of
   :class:`host.link.clients.PortBusy`, naming the holder);
2. Ctrl-C Ctrl-C then Enter get a ``>>>`` prompt within ``--timeout`` s; a port that answers
   with upright frames (COBS, a heartbeat) is named as the upright link, with what to do;
3. mpremote copies the bundle and resets the board, under a time limit of its own.

Exit status: 0 flashed; 1 not a REPL, busy, mpremote failed or timed out; 2 bad arguments.

Example::

    python -m host.boards.flash --port /dev/ttyACM0 --bundle out/firmware
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Sequence

__all__ = ["FlashError", "probe_repl", "flash", "main"]

#: what the REPL prints when it is ready for a line
PROMPT = b">>> "
#: the line rate of MicroPython's REPL on a UART (USB CDC ignores it)
REPL_BAUD = 115200


class FlashError(RuntimeError):
    """The board could not be flashed: one line saying why and what to do."""


def _open(port: str):  # noqa: ANN202 - a pyserial port
    import serial

    from host.link.clients import PortBusy, port_holders

    if not os.path.exists(port):
        raise FlashError(f"{port}: no such port (is the Pico plugged in? `ls /dev/ttyACM*`; PORT=... picks another)")
    try:
        return serial.Serial(port, REPL_BAUD, timeout=0, exclusive=True)
    except serial.SerialException as exc:
        if "exclusively lock" in str(exc):
            raise FlashError(str(PortBusy(port, port_holders(port)))) from None
        raise FlashError(f"{port}: cannot open: {exc}") from None


def _looks_like_upright(data: bytes) -> bool:
    # COBS frames of the upright link: a heartbeat decodes
    from host.link import messages as M

    try:
        frames = M.SerialStreamDecoder().feed(data)
    except Exception:  # noqa: BLE001 - garbage is simply not upright frames
        return False
    return any(m.NAME == "heartbeat" for m, _ in frames)


def probe_repl(port: str, timeout: float = 3.0) -> str:
    """Ask the port for a MicroPython prompt; returns ``"repl"``.

    Sends Ctrl-C twice (stops a running program) and Enter, and waits at most ``timeout`` s
    for ``>>>``.

    Raises
    ------
    FlashError
        No such port, busy, or no prompt within ``timeout`` s (the message says what the
        port answered instead: upright frames, other bytes, or nothing).
    """
    ser = _open(port)
    got = b""
    try:
        deadline = time.monotonic() + timeout
        next_poke = 0.0
        while time.monotonic() < deadline:
            now = time.monotonic()
            if now >= next_poke:
                ser.write(b"\r\x03\x03\r\n")
                ser.flush()
                next_poke = now + 0.5
            chunk = ser.read(4096)
            if chunk:
                got += chunk
                if PROMPT in got or b"raw REPL" in got:
                    return "repl"
            else:
                time.sleep(0.02)
    finally:
        ser.close()
    if _looks_like_upright(got):
        raise FlashError(f"{port} answers with the upright link's frames, not MicroPython's REPL: hand the REPL back "
                         f"with `upright board --port {port} mode repl` (LINK = \"usb\"), or reset the board and run "
                         "make flash within 2 s; a USB-serial adapter on UART0 cannot flash: use the Pico's own USB "
                         "(/dev/ttyACM0)")
    what = f"{len(got)} bytes that are not a prompt" if got else "nothing"
    raise FlashError(f"no MicroPython REPL on {port} within {timeout:g} s (it answered {what} to Ctrl-C): is it the "
                     "Pico's own USB port with MicroPython flashed (the .uf2 from micropython.org), not a "
                     "USB-serial adapter?")


def flash(port: str, bundle: str | Path, *, mpremote: str = "mpremote", timeout: float = 3.0,
          copy_timeout: float = 180.0) -> None:
    """Check the REPL (:func:`probe_repl`), then ``mpremote connect PORT fs cp -r BUNDLE/. : + reset``.

    Raises
    ------
    FlashError
        Not a REPL, no bundle, mpremote missing, failed, or slower than ``copy_timeout`` s.
    """
    b = Path(bundle)
    files = sorted(p for p in b.rglob("*") if p.is_file()) if b.is_dir() else []
    if not files:
        raise FlashError(f"{b}: no firmware bundle (make firmware writes it)")
    exe = mpremote if os.path.sep in mpremote else (
        shutil.which(mpremote, path=str(Path(sys.executable).parent)) or shutil.which(mpremote))
    if not exe or not os.path.exists(exe):
        raise FlashError(f"mpremote not found ({mpremote}): make setup installs it in .venv/bin")
    _say(f"flash: waiting up to {timeout:g} s for MicroPython's REPL on {port} (Ctrl-C, then a >>> prompt)...")
    probe_repl(port, timeout)
    _say(f"flash: REPL answers; copying {len(files)} files from {b} with mpremote (at most {copy_timeout:g} s), "
         "then reset")
    cmd = [exe, "connect", port, "fs", "cp", "-r", f"{b}/.", ":", "+", "reset"]
    try:
        p = subprocess.run(cmd, timeout=copy_timeout)
    except subprocess.TimeoutExpired:
        raise FlashError(f"mpremote did not finish within {copy_timeout:g} s on {port}: unplug and replug the "
                         "board, then make flash again") from None
    if p.returncode != 0:
        raise FlashError(f"mpremote failed (exit {p.returncode}) on {port}")
    _say("flash: done; the board resets into the robot (disarmed, motor off)")


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (``make flash``)."""
    ap = argparse.ArgumentParser(prog="flash", description=__doc__.splitlines()[0])
    ap.add_argument("--port", required=True, help="the Pico's USB port (default of make flash: /dev/ttyACM0)")
    ap.add_argument("--bundle", default="out/firmware", help="bundle directory (make firmware)")
    ap.add_argument("--mpremote", default="mpremote", help="mpremote executable")
    ap.add_argument("--timeout", type=float, default=3.0, help="seconds for the REPL to answer (default 3)")
    ap.add_argument("--copy-timeout", type=float, default=180.0, help="seconds for mpremote (default 180)")
    a = ap.parse_args(argv)
    if not 0 < a.timeout <= 600 or not 0 < a.copy_timeout <= 3600:
        ap.error("--timeout must be in (0, 600] and --copy-timeout in (0, 3600] seconds")
    try:
        flash(a.port, a.bundle, mpremote=a.mpremote, timeout=a.timeout, copy_timeout=a.copy_timeout)
    except FlashError as exc:
        _say(f"flash: {exc}")
        return 1
    except KeyboardInterrupt:
        _say("flash: interrupted")
        return 130
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
