"""HalPico's encoder read and host UART under CPython, with stand-ins for machine and rp2.

The PIO quadrature program pushes the count on every sampling pass (noblock: pushes are
dropped while the 4-deep RX FIFO is full), so the FIFO is never empty for long: the read
takes FIFO level + 1 values, as pico-examples does, and returns the count pushed after the
call began, in a bounded number of FIFO reads.  The stand-in state machine advances
"time" on every register access and pushes every few cycles, as the real one does.
(On the emulated board these run for real; here the logic is pinned down.)
"""

from __future__ import annotations

import collections
import importlib
import sys
import types

import pytest

from firmware import board

PUSH_EVERY = 8  # cycles between pushes (one sampling pass)
ACCESS = 60  # cycles per FIFO access from Python (a method call: hundreds on a board)


class FakeSM:
    def __init__(self, sm_id, prog, in_base=None):
        self.fifo: list[int] = []
        self.t = 0
        self.next_push = PUSH_EVERY
        self.count = 0
        self.velocity = 0  # counts per push
        self.reads = 0
        self.on = False

    def active(self, v):
        self.on = bool(v)

    def _advance(self, cycles):
        self.t += cycles
        while self.t >= self.next_push:
            self.next_push += PUSH_EVERY
            self.count = (self.count + self.velocity) & 0xFFFFFFFF
            if len(self.fifo) < 4:
                self.fifo.append(self.count & 0xFFFF)

    def rx_fifo(self):
        self._advance(ACCESS)
        return len(self.fifo)

    def get(self):
        self.reads += 1
        assert self.on
        self._advance(ACCESS)
        while not self.fifo:  # blocks until the next push
            self._advance(1)
        return self.fifo.pop(0)


class _Obj:
    def __init__(self, *a, **kw):
        self.args = a
        self.kw = kw

    def value(self, v=None):
        pass

    def read_u16(self):
        return 0x8000

    def freq(self, f):
        pass

    def duty_u16(self, d):
        pass


class FakeUART(_Obj):
    made: list["FakeUART"] = []

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        FakeUART.made.append(self)


@pytest.fixture
def hal_pico(monkeypatch):
    machine = types.ModuleType("machine")
    machine.Pin = type("Pin", (_Obj,), {"IN": 0, "OUT": 1, "PULL_UP": 1})
    machine.ADC = machine.PWM = _Obj
    machine.UART = FakeUART
    machine.mem32 = collections.defaultdict(int)  # the registers HalPico writes (address -> word)
    rp2 = types.ModuleType("rp2")
    rp2.PIO = type("PIO", (), {"SHIFT_LEFT": 0, "SHIFT_RIGHT": 1})
    rp2.asm_pio = lambda **kw: (lambda f: f)  # the program body runs only on the board
    rp2.StateMachine = FakeSM
    monkeypatch.setitem(sys.modules, "machine", machine)
    monkeypatch.setitem(sys.modules, "rp2", rp2)
    monkeypatch.delitem(sys.modules, "firmware.hal_pico", raising=False)
    mod = importlib.import_module("firmware.hal_pico")
    yield mod
    sys.modules.pop("firmware.hal_pico", None)


def test_encoder_read_is_bounded_and_fresh(hal_pico) -> None:
    hal = hal_pico.HalPico(board)
    sm = hal._sm
    sm.velocity = 1
    for k in range(500):
        # the CPU is away for a while (the rest of the tick): the FIFO fills and stays full
        sm._advance(1000 + 37 * (k % 7))
        before = sm.reads
        at_call = sm.count
        v = hal.read_encoder()
        assert 1 <= sm.reads - before <= 5  # FIFO depth + 1
        # not one of the stale values queued while the CPU was away: pushed after the
        # call began (the count rises by one a push)
        assert 0 < (v - at_call) % 65536 <= sm.count - at_call
        assert 0 <= v <= 0xFFFF


def test_encoder_read_wraps_16_bits(hal_pico) -> None:
    hal = hal_pico.HalPico(board)
    sm = hal._sm
    sm.velocity = -1
    sm._advance(100)
    assert hal.read_encoder() > 0xFF00  # counted below zero: the 16-bit counter wraps


def test_the_old_drain_never_ends(hal_pico) -> None:
    # what the board hung on: `while rx_fifo(): get()` against a program that keeps pushing
    hal = hal_pico.HalPico(board)
    sm = hal._sm
    sm._advance(500)
    n = 0
    while sm.rx_fifo() and n < 10000:
        sm.get()
        n += 1
    assert n == 10000


def test_host_uart_has_large_buffers(hal_pico) -> None:
    hal = hal_pico.HalPico(board)
    FakeUART.made.clear()
    hal.uart()
    (u,) = FakeUART.made
    assert u.args == (board.UART_ID, board.UART_BAUD)
    assert u.kw["rxbuf"] >= 1024 and u.kw["txbuf"] >= 256
    # the receive interrupt at half the FIFO (UART0 UARTIFLS.RXIFLSEL = 2); on the board:
    # tests/test_rp2040_board.py::test_the_host_uart_interrupts_at_half_its_receive_fifo
    assert (sys.modules["machine"].mem32[0x40034034] >> 3) & 7 == 2
