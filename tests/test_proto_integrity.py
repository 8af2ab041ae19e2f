"""Integrity on every carrier, and commands that cannot be replayed (issue 13 items 3 and 4).

* Ids: no single-bit error turns a board-bound command into ARM; ARM and DISARM are at
  least 3 bits apart.
* Every single- and double-bit flip of every command frame, on both byte-stream carriers
  (COBS serial frames; CAN frames in python-can's ``serial`` format, CRC in the timestamp
  field), run through the firmware's own decoders under CPython: none is acted on, every
  one is counted by a decoder error counter.
* 10,000 random drop / duplicate / reorder / delay schedules of arm/disarm traffic against
  the firmware's dispatcher and app: no arm is acted on after a later-sent disarm.  The
  same schedules with the epoch check defeated do re-arm (the test can fail).
"""

from __future__ import annotations

import random
from array import array
from itertools import combinations

import pytest

from firmware import canframe, codec, commands, framing
from firmware import msgtable as T
from firmware.app import App
from firmware.supervisor import ARMED, BALANCING, DISARMED, FAULT
import fwharness as H
from host.link import messages as M

COMMANDS = [c for c in M.MESSAGES.values() if c.DIRECTION == "to_board"]


def _bits(a: int, b: int) -> int:
    return bin(a ^ b).count("1")


def test_no_single_bit_error_makes_an_arm():
    for c in COMMANDS:
        if c.ID != T.ARM:
            assert _bits(c.ID, T.ARM) >= 2, f"{c.NAME} (id {c.ID}) is one bit from arm (id {T.ARM})"
    assert _bits(T.ARM, T.DISARM) >= 3
    # on CAN the node bits sit above the message id: a frame for another node is not ours
    assert T.MSG_BITS == 5 and T.MAX_ID == 31


# ---------------------------------------------------------------- bit flips
def _variants(cls: type[M.Message], k: int, rng: random.Random) -> list[M.Message]:
    # k messages of one class: both field bounds, then random in-range values
    out = []
    for i in range(k):
        kw = {}
        for f in cls.FIELDS:
            if f.is_raw:
                kw[f.name] = bytes(rng.randrange(256) for _ in range(f.size))
            elif i < 2:
                kw[f.name] = f.bounds[i]
            else:
                kw[f.name] = rng.randint(*f.bounds)
        out.append(cls(**kw))
    return out


def _frames(carrier: str, k: int) -> list[bytes]:
    rng = random.Random(13)
    frames = []
    for cls in COMMANDS:
        for j, m in enumerate(_variants(cls, k, rng)):
            frames.append(M.encode_serial(m, (37 * j + 5) & 0xFF) if carrier == "serial" else M.encode_serial_can(m, 1))
    return frames


def _flips(n_bits: int):
    for i in range(n_bits):
        yield (i,)
    yield from combinations(range(n_bits), 2)


_CAN_STATE = ("_state", "_i", "_dlc", "_id", "_flags", "_rcrc", "_crc", "_junk")


def _snapshots(dec, feed, frame: bytes, names: tuple[str, ...]) -> list[tuple]:
    # the decoder's state before each byte of the clean frame: a variant whose first
    # flipped bit is in byte p starts from the state before p (the bytes before p are
    # the clean ones), so only the rest of the frame is decoded again
    out = []
    for b in frame:
        out.append(tuple(getattr(dec, a) for a in names))
        feed(b)
    return out


def _run_serial(frames: list[bytes]) -> tuple[int, int, int]:
    # (variants, acted on, not counted) through framing.Decoder.scan; every variant ends
    # with a clean delimiter, so the decoder starts each one resynchronised
    dec = framing.Decoder(codec.Layout())
    scan = dec.scan
    n_var = acted = silent = 0
    for frame in frames:
        buf = bytearray(frame + b"\x00")  # the next frame's delimiter ends a damaged one
        n = len(buf)
        for flips in _flips(8 * len(frame)):
            for b in flips:
                buf[b >> 3] ^= 1 << (b & 7)
            d0 = dec.n_crc + dec.n_length + dec.n_unknown + dec.n_overrun
            i = 0
            while i < n:
                if scan(buf, i, n) >= 0:
                    acted += 1
                i = dec.next
            if dec.n_crc + dec.n_length + dec.n_unknown + dec.n_overrun == d0:
                silent += 1
            for b in flips:
                buf[b >> 3] ^= 1 << (b & 7)
            n_var += 1
    return n_var, acted, silent


def _run_serial_can(frames: list[bytes]) -> tuple[int, int, int]:
    # (variants, acted on, not counted) through canframe.SerialCanDecoder.feed; a damaged
    # frame left unfinished (its length damaged) is ended by two clean frames after it
    dec = canframe.SerialCanDecoder(codec.Layout(), 1)
    feed = dec.feed
    flush = M.encode_serial_can(M.BY_NAME["host_heartbeat"](), 1) * 2
    n_var = acted = silent = 0
    for frame in frames:
        buf = bytearray(frame)
        n = len(buf)
        snaps = _snapshots(dec, feed, frame, _CAN_STATE)
        for flips in _flips(8 * n):
            for b in flips:
                buf[b >> 3] ^= 1 << (b & 7)
            p = flips[0] >> 3
            (dec._state, dec._i, dec._dlc, dec._id, dec._flags, dec._rcrc, dec._crc, dec._junk) = snaps[p]
            d0 = dec.n_crc + dec.n_length + dec.n_unknown + dec.n_framing + dec.n_sync
            for i in range(p, n):
                if feed(buf[i]) >= 0:
                    acted += 1
            if dec._state != 0:
                for x in flush:
                    m = feed(x)
                    if m >= 0 and m != T.HOST_HEARTBEAT:
                        acted += 1
            if dec.n_crc + dec.n_length + dec.n_unknown + dec.n_framing + dec.n_sync == d0:
                silent += 1
            for b in flips:
                buf[b >> 3] ^= 1 << (b & 7)
            n_var += 1
    return n_var, acted, silent


@pytest.mark.slow
def test_every_single_and_double_bit_flip_of_every_command_frame_is_dropped_and_counted():
    serial = _run_serial(_frames("serial", 12))
    can = _run_serial_can(_frames("can", 7))
    assert serial[1:] == (0, 0), f"serial: {serial[1]} acted on, {serial[2]} not counted of {serial[0]}"
    assert can[1:] == (0, 0), f"CAN on a stream: {can[1]} acted on, {can[2]} not counted of {can[0]}"
    assert serial[0] + can[0] >= 10**6, (serial[0], can[0])


def test_the_flip_harness_sees_a_clean_frame():
    # the same harness passes undamaged frames (so "none acted on" above is not vacuous)
    dec = framing.Decoder(codec.Layout())
    got = [dec.feed(b) for b in M.encode_serial(M.Disarm(), 1)]
    assert T.DISARM in got
    cdec = canframe.SerialCanDecoder(codec.Layout(), 1)
    assert T.DISARM in [cdec.feed(b) for b in M.encode_serial_can(M.Disarm(), 1)]
    # a payload flip that the old carrier (no CRC) passed is now dropped as a CRC error
    f = bytearray(M.encode_serial_can(M.SetReference(x_um=1000), 1))
    f[10] ^= 0x01
    assert all(cdec.feed(b) < 0 for b in f) and cdec.n_crc == 1


# ---------------------------------------------------------------- replay schedules
class _Hal(H.StandInHal):
    # sensors at rest upright; the ADC rails while `rail` (a fault the board latches)
    rail = False

    def __init__(self) -> None:
        super().__init__(inc=2000)

    def read_angle_raw(self) -> int:
        return 0 if self.rail else 2048


class _Null:
    def send(self, mid, seq, vals, voff) -> None:
        pass


class _Board:
    def __init__(self) -> None:
        self.hal = _Hal()
        self.app = App(self.hal, config={"pot_offset": 2048, "watchdog_ms": 0, "stall_ms": 0, "epoch": 0})
        self.disp = commands.Dispatcher(self.app, codec.Layout(), _Null())
        self.buf = bytearray(12)

    def handle(self, msg: M.Message) -> int:
        p = msg.payload()
        self.buf[2:2 + len(p)] = p
        return self.disp.handle(msg.ID, 0, self.buf, 2)


_ARM, _DISARM, _CLEAR = M.BY_NAME["arm"], M.BY_NAME["disarm"], M.BY_NAME["clear_faults"]


def _schedule(board: _Board, rng: random.Random, defeat_epoch: bool = False) -> int:
    """One schedule; returns the number of unintended arms (an arm acted on after a later-sent disarm)."""
    app = board.app
    # start disarmed, no fault
    board.handle(_DISARM())
    board.handle(_CLEAR())
    board.hal.rail = False
    app.step()
    # the host's intent: arms (each with retries: the same frame again) and disarms, in
    # order; each arm carries the epoch of the last heartbeat the host saw, which may be
    # stale (the board's epoch at a random earlier point of the schedule)
    history = [app.epoch]
    sent: list[tuple[int, M.Message]] = []  # (send index, message)
    t = 0.0
    timed: list[tuple[float, int, int]] = []  # (delivery time, order, send index)
    n_ops = rng.randint(2, 10)
    for _ in range(n_ops):
        r = rng.random()
        if r < 0.45:
            msg: M.Message = _ARM(epoch=rng.choice(history[-3:]))
            copies = 1 + rng.randint(0, 3)  # retries of the same arm
        elif r < 0.9:
            msg = _DISARM()
            copies = 1 + rng.randint(0, 2)
        else:
            msg = _CLEAR()
            copies = 1
        for _ in range(copies):
            idx = len(sent)
            sent.append((idx, msg))
            t += rng.expovariate(1.0)
            # the carrier: drop, duplicate, delay (which reorders)
            if rng.random() < 0.15:
                continue
            for _ in range(1 + (rng.random() < 0.2) + (rng.random() < 0.05)):
                timed.append((t + rng.expovariate(0.3) if rng.random() < 0.5 else t, len(timed), idx))
        # the host sees a heartbeat now and then (its epoch as it is at that moment)
        history.append(app.epoch)
    timed.sort()
    unintended = 0
    disarm_seen = -1  # largest send index of a disarm the board processed
    for _, _, idx in timed:
        msg = sent[idx][1]
        # board time passes between frames; sometimes a fault (the ADC rails for a tick)
        board.hal.rail = rng.random() < 0.05
        app.step()
        board.hal.rail = False
        if msg.NAME == "arm" and defeat_epoch:
            msg = _ARM(epoch=app.epoch)  # what a protocol without the epoch would do
        before = app.sup.state
        r = board.handle(msg)
        history.append(app.epoch)
        if msg.NAME == "disarm":
            disarm_seen = max(disarm_seen, idx)
        elif msg.NAME == "arm" and r == T.OK and before == DISARMED and app.sup.state == ARMED:
            if disarm_seen > idx:
                unintended += 1
        assert app.sup.state in (DISARMED, ARMED, BALANCING, FAULT)
    return unintended


@pytest.mark.slow
def test_10000_lossy_schedules_never_arm_after_a_later_disarm():
    board = _Board()
    rng = random.Random(2013)
    bad = sum(_schedule(board, rng) for _ in range(10_000))
    assert bad == 0


def test_without_the_epoch_the_same_schedules_do_rearm():
    # the check above can fail: defeat the epoch and lossy schedules re-arm after a disarm
    board = _Board()
    rng = random.Random(2013)
    bad = sum(_schedule(board, rng, defeat_epoch=True) for _ in range(2000))
    assert bad > 0


def test_stale_and_repeated_arms_are_refused_with_their_own_reason():
    board = _Board()
    app = board.app
    e = app.epoch
    assert board.handle(_ARM(epoch=e)) == T.OK and app.sup.state == ARMED
    # a repeat while armed changes nothing
    assert board.handle(_ARM(epoch=e)) == T.OK and app.sup.state == ARMED
    assert board.handle(_DISARM()) == T.OK and app.epoch != e
    e1 = app.epoch
    # the same arm after the disarm: refused, still disarmed
    assert board.handle(_ARM(epoch=e)) == T.R_STALE_EPOCH and app.sup.state == DISARMED
    # a fault draws a new token too; clear_faults again
    board.hal.rail = True
    app.step()
    board.hal.rail = False
    assert app.sup.state == FAULT and app.epoch not in (e, e1)
    e2 = app.epoch
    assert board.handle(_CLEAR()) == T.OK and app.epoch not in (e, e1, e2)
    assert board.handle(_ARM(epoch=e2)) == T.R_STALE_EPOCH
    assert board.handle(_ARM(epoch=app.epoch)) == T.OK and app.sup.state == ARMED


def test_only_a_host_heartbeat_or_a_set_point_feeds_the_watchdog():
    hal = _Hal()
    app = App(hal, config={"pot_offset": 2048, "stall_ms": 0, "epoch": 0})
    board = _Board.__new__(_Board)
    board.hal, board.app, board.buf = hal, app, bytearray(12)
    board.disp = commands.Dispatcher(app, codec.Layout(), _Null())
    assert board.handle(_ARM(epoch=app.epoch)) == T.OK
    wd = app.sup.wd_ticks
    assert wd > 0
    # a monitor polling the board (requests, parameter reads) does not keep it alive
    for _ in range(wd + 2):
        board.handle(M.BY_NAME["request"](msg_id=T.HEARTBEAT))
        board.handle(M.BY_NAME["param_get"](index=0))
        app.step()
    assert app.sup.state == FAULT
    board.handle(_CLEAR())
    assert board.handle(_ARM(epoch=app.epoch)) == T.OK
    for k in range(3 * wd):
        board.handle(M.BY_NAME["host_heartbeat"]() if k % 2 else M.BY_NAME["set_reference"](x_um=0))
        app.step()
    assert app.sup.state in (ARMED, BALANCING)


@pytest.mark.parametrize("carrier", ["serial", "can"])
def test_flip_count_per_frame_is_what_the_bits_give(carrier):
    # bookkeeping of the big test: C(n, 1) + C(n, 2) variants for a frame of n bits
    f = _frames(carrier, 1)[0]
    n = 8 * len(f)
    assert sum(1 for _ in _flips(n)) == n + n * (n - 1) // 2
    assert array  # (array used by the harness helpers' types)
