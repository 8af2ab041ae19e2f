# Persistent configuration: the parameters and the active gain table, kept in two copies
# (slots A and B: two files on the board's LittleFS, or in a directory on the unix port).
#
# A copy (little-endian):
#   "UPCF"  magic
#   u8      record format (_FORMAT)
#   u8      number of parameters   (msgtable.N_PARAMS of the firmware that wrote it)
#   u16     number of table ints   (gain table length)
#   u32     sequence number        (each save: newest + 1, mod 2**30)
#   i32 x n parameters, i32 x m table
#   u16     CRC-16/CCITT-FALSE (big-endian) of everything before it
# A save writes the slot that does not hold the newest valid copy, so the newest valid copy
# is never touched: cut anywhere (power, reset, a killed process), the slot being written
# is either complete (its CRC holds: the new set) or not (the other slot: the old set).
# The copy is written under a temporary name and renamed over its slot (atomic on
# LittleFS and POSIX), so a cut first save leaves no slot rather than a torn one (which
# would read as CORRUPT); the CRC and the second copy guard against what a rename cannot:
# a torn or decayed copy on the flash itself.
# Loading takes the newest copy whose magic, shape, length, CRC and content check (the
# caller's: parameter ranges, the controller's table check) all pass.
#
#   store = ConfigStore(root)             root: "" (board: the filesystem root) or a directory
#   st, params, table = store.load(check) st: LOADED, EMPTY (no copy at all: first start) or
#                                         CORRUPT (copies there, none valid)
#   store.load(check, migrate, params_ok) also keeps what a firmware update left readable: a
#                                         copy whose table has another layout (an older gain-table
#                                         version) gives MIGRATED (its table converted by
#                                         migrate(table), see upgrade()) or PARAMS_ONLY (the
#                                         parameters, table None: the caller keeps its own);
#                                         a copy with fewer parameters (an older firmware's)
#                                         loads MIGRATED, the caller defaulting the rest
#   store.save(params, table)             -> the new sequence number; OSError on a write error
# Never called from the control tick (it allocates and may wait for flash erases): the app
# runs a requested save between ticks, only while the motor is off (firmware/app.py).

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

import os
import struct

from . import crc16

LOADED = const(0)
EMPTY = const(1)
CORRUPT = const(2)
# 3 is the app's "no storage" (msgtable S_CFG_STATUS)
MIGRATED = const(4)
PARAMS_ONLY = const(5)
STATUS_NAMES = ("loaded", "empty", "corrupt", "no storage", "migrated", "params only")

# Gain-table layouts an update can convert (upgrade()): (old version, old length, where the
# new ints go, the ints).  Version 1 -> 2 appended EST (issue 27: 0, the full estimator the
# version-1 firmware ran); tests/test_store_migration.py checks this against firmware/gains.py.
UPGRADES = ((1, 114, 114, (0,)),)

MAGIC = b"UPCF"
_FORMAT = const(1)
_HEAD = const(12)
_SEQ_MASK = const(0x3FFFFFFF)
_SEQ_HALF = const(0x20000000)
# written in pieces of this many bytes (a cut then lands between pieces as well as in them)
_CHUNK = const(64)
NAMES = ("cfg_a.bin", "cfg_b.bin")


def newer(a, b):
    # sequence number a is newer than b (serial-number arithmetic mod 2**30)
    d = (a - b) & _SEQ_MASK
    return 0 < d < _SEQ_HALF


def encode(seq, params, table, crc_table=None):
    # one copy's bytes
    n = len(params)
    m = len(table)
    buf = bytearray(_HEAD + 4 * (n + m) + 2)
    buf[0:4] = MAGIC
    struct.pack_into("<BBHI", buf, 4, _FORMAT, n, m, seq & _SEQ_MASK)
    o = _HEAD
    for v in params:
        struct.pack_into("<i", buf, o, v)
        o += 4
    for v in table:
        struct.pack_into("<i", buf, o, v)
        o += 4
    c = crc16.compute(crc_table if crc_table is not None else crc16.make_table(), buf, 0, o)
    buf[o] = c >> 8
    buf[o + 1] = c & 0xFF
    return buf


def upgrade(table, version, length):
    # a saved table of an older layout converted to (version, length) by UPGRADES (the
    # header's version and length rewritten), or None when no step converts it
    t = list(table)
    steps = 0
    while steps < len(UPGRADES) + 1:
        if len(t) == length and t[0] == version and t[2] == length:
            return t
        for u in UPGRADES:
            if t[0] == u[0] and len(t) == u[1] and t[2] == u[1]:
                t = t[:u[2]] + list(u[3]) + t[u[2]:]
                t[0] = u[0] + 1
                t[2] = len(t)
                break
        else:
            return None
        steps += 1
    return None


def decode(data, n_params, n_table, crc_table=None):
    # (seq, params, table) of a copy, or None if it is not a complete, intact copy of this
    # shape (n_table < 0: any table length, the one its header gives; n_params < 0: any
    # number of parameters up to -n_params, the one its header gives)
    if data is None or len(data) < _HEAD + 2 or data[0:4] != MAGIC:
        return None
    fmt, n, m, seq = struct.unpack_from("<BBHI", data, 4)
    if n_table < 0:
        n_table = m
    if n_params < 0:
        if n > -n_params:
            return None
        n_params = n
    if len(data) != _HEAD + 4 * (n_params + n_table) + 2:
        return None
    if fmt != _FORMAT or n != n_params or m != n_table:
        return None
    if crc16.compute(crc_table if crc_table is not None else crc16.make_table(), data, 0, len(data)) != 0:
        return None
    o = _HEAD
    params = [0] * n
    for i in range(n):
        params[i] = struct.unpack_from("<i", data, o)[0]
        o += 4
    table = [0] * m
    for i in range(m):
        table[i] = struct.unpack_from("<i", data, o)[0]
        o += 4
    return seq & _SEQ_MASK, params, table


class ConfigStore:
    def __init__(self, root="", n_params=0, n_table=0):
        # root: directory of the two files ("" = the current directory, the board's root);
        # n_params/n_table: the shape a valid copy must have (0: take the shape of the
        # first save or of the caller's load)
        if root and not root.endswith("/"):
            root = root + "/"
        self.paths = (root + NAMES[0], root + NAMES[1])
        self.n_params = n_params
        self.n_table = n_table
        self.seq = 0  # newest valid copy's sequence number (0: none)
        self.slot = -1  # its slot (-1: none)
        self.status = EMPTY
        self.valid = 0  # valid copies found by the last load (0, 1 or 2)
        self.crc = crc16.make_table()

    def _read(self, path):
        try:
            with open(path, "rb") as f:
                return f.read()
        except OSError:
            return None

    def _older(self, rec, check, migrate, params_ok):
        # (status, table) of an intact copy whose table has another layout than ours (a
        # firmware update), or None: converted by migrate(table) and passing check -> MIGRATED;
        # else its parameters alone if params_ok(params) -> PARAMS_ONLY (table None)
        # A table of our length is dropped only when converted from an older version: our
        # length with content failing the check (a bad version included) stays CORRUPT.
        # An older firmware's copy may hold fewer parameters (params_ok and check see the
        # shorter list; the caller gives the rest their defaults): with our table layout
        # and passing check, it is MIGRATED as it is.
        params, table = rec[1], rec[2]
        if params_ok is None or not params_ok(params):
            return None
        fewer = len(params) < self.n_params
        if fewer and len(table) == self.n_table and (check is None or check(params, table)):
            return MIGRATED, table
        t = migrate(table) if migrate is not None else None
        if t is not None and t != table and len(t) == self.n_table and (check is None or check(params, t)):
            return MIGRATED, t
        if len(table) == self.n_table:
            return None
        return PARAMS_ONLY, None

    def load(self, check=None, migrate=None, params_ok=None):
        # -> (status, params, table): the newest valid copy, or (EMPTY/CORRUPT, None, None).
        # check(params, table) -> True: the caller's content check (ranges, table check);
        # migrate(table) -> the table converted to our layout (or None), params_ok(params) ->
        # True: with both, an intact copy of another table layout is MIGRATED / PARAMS_ONLY
        # (the newest usable copy wins, whatever its status)
        best = None
        found = 0
        self.valid = 0
        for slot in range(2):
            data = self._read(self.paths[slot])
            if data is None:
                continue
            found += 1
            rec = decode(data, self.n_params, self.n_table, self.crc)
            st = LOADED
            if rec is None or (check is not None and not check(rec[1], rec[2])):
                rec = decode(data, -self.n_params if params_ok is not None else self.n_params, -1, self.crc)
                old = None if rec is None else self._older(rec, check, migrate, params_ok)
                if old is None:
                    continue
                st = old[0]
                rec = (rec[0], rec[1], old[1])
            self.valid += 1
            if best is None or newer(rec[0], best[0]):
                best = (rec[0], rec[1], rec[2], slot, st)
        if best is None:
            self.seq = 0
            self.slot = -1
            self.status = CORRUPT if found else EMPTY
            return self.status, None, None
        self.seq = best[0]
        self.slot = best[3]
        self.status = best[4]
        return best[4], best[1], best[2]

    def save(self, params, table):
        # write a new copy into the slot not holding the newest valid one; -> its seq
        self.n_params = len(params)
        self.n_table = len(table)
        seq = (self.seq + 1) & _SEQ_MASK
        if seq == 0:
            seq = 1
        slot = 1 if self.slot == 0 else 0
        buf = encode(seq, params, table, self.crc)
        mv = memoryview(buf)
        tmp = self.paths[slot] + ".new"
        with open(tmp, "wb") as f:
            for o in range(0, len(buf), _CHUNK):
                f.write(mv[o:o + _CHUNK])
            f.flush()
        os.rename(tmp, self.paths[slot])
        self.seq = seq
        self.slot = slot
        self.status = LOADED
        return seq
