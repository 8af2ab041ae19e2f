# The app's gain table: an uploaded table (GAINS_COMMIT, from commands.Dispatcher) checked
# again and installed while the motor is off, a saved one installed at start-up, and the
# table's CRC-16 (gains.CRC, VERSION).  A part of firmware/app.py's App; never in the tick.

from . import crc16
from . import fixmath
from . import msgtable as T
from .supervisor import DISARMED, FAULT, F_CONFIG, F_GAINS


class TableUpload:
    def gains_apply(self, buf, nbytes):
        return self.gains_apply_crc(buf, nbytes, -1)

    def gains_apply_crc(self, buf, nbytes, crc):
        # a complete, CRC-checked table from the dispatcher: int32 little-endian in
        # the layout of firmware/gains.py; re-checked here before it replaces the live one.
        # crc: its CRC-16 as the dispatcher checked it chunk by chunk (the table's CRC, the
        # same bytes: not computed again), -1: compute it
        if self.sup.state != DISARMED and self.sup.state != FAULT:
            return T.R_ARMED
        n = nbytes >> 2
        if nbytes & 3 or n != self.ctrl.length:
            return T.R_BAD_LENGTH
        sc = self.ctrl.scratch
        for i in range(n):
            v = fixmath.s32_le(buf, 4 * i)
            if v is None:
                return T.R_UNSTABLE
            sc[i] = v
        r = self.ctrl.validate(sc, n, self.version)
        if r != T.OK:
            return r
        self._install_table(sc, n, crc)
        self._apply_params()
        self.sup.faults &= ~(F_GAINS | F_CONFIG)
        self.config_bad = False
        return T.OK

    def _install_table(self, src, n, crc=-1):
        # a checked table becomes the live one (upload or saved configuration)
        t = self.table
        for i in range(n):
            t[i] = src[i]
        self.gains_crc = crc if crc >= 0 else self._table_crc(t, n)
        self.sup.ready = True
        off = self.off
        self.ctrl.load(t)
        self.sensors.load(t, off)
        self.motor.load(t, off)
        self.rate = t[off["RATE"]]

    def _table_crc(self, t, n):
        # CRC-16/CCITT-FALSE of the table as int32 little-endian (gains.CRC, the upload CRC)
        tb = self._crc_table
        c = crc16.INIT
        for i in range(n):
            v = t[i]
            c = crc16.update(tb, c, v & 0xFF)
            c = crc16.update(tb, c, (v >> 8) & 0xFF)
            c = crc16.update(tb, c, (v >> 16) & 0xFF)
            c = crc16.update(tb, c, (v >> 24) & 0xFF)
        return c
