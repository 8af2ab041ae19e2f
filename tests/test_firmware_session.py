"""Nothing from before a reset arms after it; a corrupted command does not act (issue 23, item 3).

* many boots on the MicroPython unix port, each as main.py starts the app (the persisted boot
  counter and session seed, firmware/boot.py and firmware/session.py): every boot draws another
  30-bit arming token, and the ARM frames captured in earlier boots are all refused
  (stale_epoch) -- also with os.urandom the same at every power-up (as on the emulated RP2040:
  CPython, os.urandom replaced), where the persisted seed alone makes the boots differ;
* a whole gain upload captured in one boot (begin, chunks, commit), replayed byte for byte into
  the next boot: refused at its begin (stale_epoch), nothing applied; in its own boot it applies;
* the token generator is a x -> a*x + c mod 2**30 LCG in small ints (full period);
* random bit flips in the commands that move the cart (and in a gain commit), with the frame's
  CRC-16 made to pass -- the corruption the CRC misses -- never act: each is refused by its
  CRC-32 check.
"""

from __future__ import annotations

import random
import struct

import pytest

from firmware import msgtable as T
import fwharness as H
from host.boards.mpyrun import run_unix
from host.link import messages as M

BOOTS = 300

SCRIPT = H.FAKE_HAL + """
from firmware import codec, commands, msgtable as T
from firmware.app import App
from firmware.boot import boot_count
from firmware.crc32 import seal
from firmware.session import seed

DIR = '@@DIR@@'
LAYOUT = codec.Layout()

class Null:
    def send(self, mid, seq, vals, voff):
        pass

def frame(mid, *vals):
    # a command's payload as the link hands it (buf[2:]), its check sealed
    buf = bytearray(16)
    v = list(vals) + [0] * 4
    seal(LAYOUT, mid, v, 0, buf, 2)
    LAYOUT.pack(mid, v, 0, buf, 2)
    return buf

def start():
    # what main.py does at start-up (boot counter, session seed), then the app and its link
    cfg = {'boot': boot_count(DIR + '/boot_count'), 'seed': seed(DIR + '/session_seed'), 'stall_ms': 0}
    app = App(Hal(), config=cfg)
    return app, commands.Dispatcher(app, LAYOUT, Null())

captured = []
tokens = []
acted = 0
tried = 0
for b in range(@@BOOTS@@):
    app, d = start()
    app.step()
    tokens.append(app.epoch)
    for buf in captured[-5:] + captured[:1]:
        tried += 1
        if d.handle(T.ARM, 1, buf, 2) == T.OK:
            acted += 1
    # this boot's own arm: accepted (positive control), then captured for the next boots
    buf = frame(T.ARM, app.epoch)
    if b % 50 == 0:
        print('own', d.handle(T.ARM, 1, buf, 2))
        d.handle(T.DISARM, 1, frame(T.DISARM), 2)
    captured.append(buf)
print('acted', acted, tried)
print('distinct', len(set(tokens)), len(tokens))
print('boot', app.boot)
"""


@pytest.fixture(scope="module")
def boots(tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[int]]:
    d = tmp_path_factory.mktemp("boots")
    out = run_unix(SCRIPT.replace("@@DIR@@", str(d)).replace("@@BOOTS@@", str(BOOTS)), timeout=120)
    res: dict[str, list[int]] = {}
    for line in out.splitlines():
        if line.strip():
            k, *v = line.split()
            res.setdefault(k, []).extend(int(x) for x in v)
    return res


def test_a_captured_arm_never_arms_a_later_boot(boots) -> None:
    assert boots["own"] and set(boots["own"]) == {T.OK}  # in its own boot it arms
    assert boots["acted"][0] == 0 and boots["acted"][1] > 5 * BOOTS
    assert boots["distinct"] == [BOOTS, BOOTS]
    assert boots["boot"] == [BOOTS & 0xFF]


def test_boots_differ_even_when_urandom_repeats(tmp_path, monkeypatch) -> None:
    # the emulated RP2040's urandom is the same at every power-up: the persisted seed carries
    # the difference (CPython with os.urandom replaced: the module is the firmware's own)
    import os

    from firmware.app import App
    from firmware.session import seed
    from fwharness import FAKE_HAL

    monkeypatch.setattr(os, "urandom", lambda n: b"\x2a" * n)
    ns: dict = {}
    exec(FAKE_HAL, ns)
    tokens = []
    for b in range(BOOTS):
        app = App(ns["Hal"](), config={"boot": 1, "seed": seed(str(tmp_path / "session_seed"))})
        tokens.append(app.epoch)
    assert len(set(tokens)) == BOOTS
    # without the persisted seed every such boot would start alike (the defect the seed fixes)
    same = {App(ns["Hal"](), config={"boot": 1}).epoch for _ in range(5)}
    assert len(same) == 1


UPLOAD = H.FAKE_HAL + """
from firmware import codec, commands, crc16, msgtable as T, gains as G
from firmware.app import App
from firmware.crc32 import of as crc32_of, seal
from firmware.session import seed

DIR = '@@DIR@@'
LAYOUT = codec.Layout()
TABLE = crc16.make_table()

class Null:
    def send(self, mid, seq, vals, voff):
        pass

def start():
    app = App(Hal(), config={'seed': seed(DIR + '/session_seed'), 'stall_ms': 0})
    return app, commands.Dispatcher(app, LAYOUT, Null())

def frames(app, blob):
    # the whole upload as the link would hand it: (mid, payload buffer) per frame
    out = []
    n = len(blob)
    def add(mid, *vals):
        buf = bytearray(16)
        v = list(vals) + [0] * 4
        LAYOUT.pack(mid, v, 0, buf, 2)
        out.append((mid, buf))
        return buf
    add(T.GAINS_BEGIN, n, crc16.compute(TABLE, blob, 0, n), app.epoch)
    for off in range(0, n, 6):
        buf = add(T.GAINS_CHUNK, off)
        for i in range(6):
            buf[4 + i] = blob[off + i] if off + i < n else 0
    add(T.GAINS_COMMIT, crc32_of(blob))
    return out

# another good table: the default with a softer gain in its force row (still valid)
flat = list(G.FLAT)
blob = bytearray(4 * len(flat))
for i in range(len(flat)):
    x = flat[i] & 0xFFFFFFFF
    for j in range(4):
        blob[4 * i + j] = (x >> (8 * j)) & 0xFF
blob[-4] ^= 0  # same table bytes: what matters is whether the upload is applied at all
app, d = start()
app.step()
up = frames(app, blob)
rs = [d.handle(m, 1, b, 2) for m, b in up]
print('own', rs[0], rs[-1])
# the next boot: the same frames replayed
app2, d2 = start()
app2.step()
crc0 = app2.gains_crc
calls = []
orig = app2.gains_apply_crc
def spy(buf, n, crc):
    calls.append(n)
    return orig(buf, n, crc)
app2.gains_apply_crc = spy
d2 = commands.Dispatcher(app2, LAYOUT, Null())
rs = [d2.handle(m, 1, b, 2) for m, b in up]
print('replay', rs[0], rs[1], rs[-1], len(calls), int(app2.gains_crc == crc0))
"""


def test_a_whole_upload_replayed_after_a_reset_is_refused(tmp_path) -> None:
    out = run_unix(UPLOAD.replace("@@DIR@@", str(tmp_path)), timeout=60)
    got = {ln.split()[0]: [int(x) for x in ln.split()[1:]] for ln in out.splitlines() if ln.strip()}
    assert got["own"][:2] == [T.OK, T.OK]  # in its own session the upload applies
    begin, chunk, commit, applied, same = got["replay"]
    assert begin == T.R_STALE_EPOCH and chunk == T.R_BAD_SEQUENCE and commit == T.R_BAD_SEQUENCE
    assert applied == 0 and same == 1


def test_token_generator_is_the_full_period_lcg() -> None:
    from firmware.app import App

    class _T:
        epoch = 0

    rng = random.Random(5)
    a, c, m = 0x41C64E6D % (1 << 30), 12345, 1 << 30
    for _ in range(2000):
        t = _T()
        t.epoch = x = rng.randrange(m)
        App._new_token(t)
        assert t.epoch == (a * x + c) % m
    assert a % 4 == 1 and c % 2 == 1  # Hull-Dobell: full period 2**30


# ---------------------------------------------------------------- corruption
def _corrupt_acts(msg: M.Message, trials: int, rng: random.Random, target) -> tuple[int, int]:
    # random bit flips in id + payload, the frame's CRC-16 recomputed (so it passes): how many
    # of the corrupted frames does the dispatcher accept as a command that moves the cart
    from firmware import codec, commands

    from array import array

    layout = codec.Layout()
    raw = bytearray([msg.ID, 1]) + bytearray(msg.payload())
    want = array("i", [0] * 8)
    layout.unpack(msg.ID, raw, 2, want, 0)
    seen = array("i", [0] * 8)
    acts = refused_check = 0
    for _ in range(trials):
        f = bytearray(raw)
        for _ in range(rng.randint(1, 6)):
            bit = rng.randrange(8 * len(f))
            if bit // 8 == 1:
                continue  # seq is not protected and not part of the command
            f[bit // 8] ^= 1 << (bit % 8)
        mid = f[0]
        if mid > T.MAX_ID or layout.plen[mid] == 0xFF or layout.plen[mid] != len(f) - 2:
            continue  # the decoder drops it (unknown id or wrong length)
        if f == raw:
            continue
        tg = target()
        d = commands.Dispatcher(tg, layout, _Null())
        r = d.handle(mid, 1, f, 2)
        if r == T.R_BAD_CHECK:
            refused_check += 1
        if r == T.OK and (mid in T.CHECKED or mid == T.GAINS_COMMIT):
            # accepted: it acts unless the firmware reads the very command that was sent (a flip
            # in the top 2 bits of a u32, which the firmware does not keep, changes nothing)
            n = layout.unpack(mid, f, 2, seen, 0)
            if mid != msg.ID or list(seen[:n]) != list(want[:n]):
                acts += 1
    return acts, refused_check


class _Null:
    def send(self, mid, seq, vals, voff):
        pass


def _app():
    from firmware.app import App
    from fwharness import FAKE_HAL

    ns: dict = {}
    exec(FAKE_HAL, ns)
    return App(ns["Hal"](), config={"epoch": 12345, "stall_ms": 0, "watchdog_ms": 0})


@pytest.mark.parametrize("msg", [
    M.Arm(epoch=12345),
    M.SetReference(x_um=200000),
    M.ParamSet(index=T.P_TILT_LIMIT, value=600),
    M.Excite(mode=1, div=4, amp_mn=200),
], ids=lambda m: m.NAME)
def test_corrupted_commands_that_pass_the_frame_crc_never_act(msg) -> None:
    # 4000 corruptions per command, each one the frame CRC-16 would have let through: the check
    # (CRC-32: 2**-30, param_set 2**-24) refuses them all; on the wire a random corruption also
    # has to pass the CRC-16 first (2**-16): < 1e-9 per corrupted frame in total
    rng = random.Random(msg.ID)
    app = _app()
    for _ in range(20):
        app.step()
    acts, refused = _corrupt_acts(msg, 4000, rng, lambda: app)
    assert acts == 0
    assert refused > 1000  # most corruptions reach the check (the rest are dropped earlier)
