# MCP2515 stand-alone CAN controller on SPI (the RP2040 has no CAN controller of its own).
# Register-level driver, allocation-free after __init__: every SPI transaction goes through
# one preallocated tx/rx buffer pair and memoryviews made once per length, with
# spi.write_readinto(); the chip-select is a machine.Pin driven by hand; the INT pin
# (active low, open drain on the module) is polled, no interrupt handler.
#
#   drv = MCP2515(spi, cs, irq=None)     spi: machine.SPI mode 0, <= 10 MHz; cs, irq: Pins
#   drv.init(bitrate, xtal_hz, node)     -> OK or E_ABSENT / E_BITRATE / E_MODE (start-up)
#   drv.pending()                        INT low (or no INT pin): something to look at
#   drv.flags()                          CANINTF in drv.intf, EFLG in drv.eflg (one transaction)
#   drv.read_rx(k)                       RXBk -> drv.rid, drv.rdlc, drv.rdata[0:8] (kept until the
#                                        next read_rx); clears RXkIF
#   drv.load_tx(k, buf, off) / rts(m)    LOAD TX BUFFER k from buf[off:off+13] / request to send
#   drv.load_frame(k, frame)             LOAD TX BUFFER k from a 14-byte transaction buffer
#   drv.tx_busy()                        TXREQ bits of TXB0..2 as a 3-bit mask (READ STATUS)
#   drv.counters()                       TEC, REC -> drv.tec, drv.rec
#   drv.clear_errors()                   ERRIF/MERRF and the RXnOVR flags cleared
#   drv.abort()                          abort every pending transmission (bus-off)
#
# Bit timing: TQ = 2 (BRP + 1) / Fosc; a bit is SYNC (1 TQ) + PRSEG + PHSEG1 + PHSEG2.  The
# table holds the settings for the common module crystals; each puts the sample point at
# 75-87.5 % (CiA 301's 87.5 % where the TQ count allows).  8 MHz cannot make 1 Mbit/s: that
# is 4 TQ a bit, below the chip's minimum of 6 (PRSEG + PHSEG1 >= 3 TQ, PHSEG2 >= 2 TQ, as
# Linux mcp251x's tseg1_min/tseg2_min): refused (E_BITRATE) -- use a 16 MHz module.
#
# Acceptance: both masks compare the 6 node bits of the 11-bit id (0x7E0) and every filter
# holds node << 5, so only this node's frames (any message id) reach the receive buffers;
# extended frames never match (EXIDE = 0).  RXB0 rolls over into RXB1 (BUKT) when full.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

# instructions
_RESET = const(0xC0)
_READ = const(0x03)
_WRITE = const(0x02)
_MODIFY = const(0x05)
_STATUS = const(0xA0)
_RXSTATUS = const(0xB0)
_LOAD_TX = const(0x40)  # | (k << 1): TXBk from SIDH
_RTS = const(0x80)      # | mask of TXB0..2
_READ_RX = const(0x90)  # | (k << 2): RXBk from SIDH (clears RXkIF when CS rises)
# registers
R_RXF0 = const(0x00)
R_RXF3 = const(0x10)
R_TEC = const(0x1C)
R_REC = const(0x1D)
R_RXM0 = const(0x20)
R_CNF3 = const(0x28)
R_CNF2 = const(0x29)
R_CNF1 = const(0x2A)
R_CANINTE = const(0x2B)
R_CANINTF = const(0x2C)
R_EFLG = const(0x2D)
R_CANSTAT = const(0x0E)
R_CANCTRL = const(0x0F)
R_TXB0CTRL = const(0x30)
R_TXB1CTRL = const(0x40)
R_TXB2CTRL = const(0x50)
R_RXB0CTRL = const(0x60)
R_RXB1CTRL = const(0x70)
# CANINTF / CANINTE bits
RX0IF = const(0x01)
RX1IF = const(0x02)
TX0IF = const(0x04)
TX1IF = const(0x08)
TX2IF = const(0x10)
ERRIF = const(0x20)
MERRF = const(0x80)
# EFLG bits
EWARN = const(0x01)
RXWAR = const(0x02)
TXWAR = const(0x04)
RXEP = const(0x08)
TXEP = const(0x10)
TXBO = const(0x20)
RX0OVR = const(0x40)
RX1OVR = const(0x80)
# CANCTRL / CANSTAT
_MODE_MASK = const(0xE0)
MODE_NORMAL = const(0x00)
MODE_LOOPBACK = const(0x40)
MODE_LISTEN = const(0x60)
MODE_CONFIG = const(0x80)
_ABAT = const(0x10)
# results of init()
OK = const(0)
E_ABSENT = const(1)   # no answer on SPI (CANSTAT after reset / registers do not read back)
E_BITRATE = const(2)  # no CNF setting for this bit rate and crystal
E_MODE = const(3)     # the chip did not enter normal mode
_TRIES = const(50)    # bounded polls of CANSTAT (a missing chip must not hang start-up)

# (xtal_hz, bitrate, CNF1, CNF2, CNF3): SJW 1 TQ, BTLMODE = 1 (PHSEG2 from CNF3), 1 sample
#  16 MHz 500k: BRP 0 (TQ 125 ns), 16 TQ = 1 + PRSEG 5 + PHSEG1 8 + PHSEG2 2 -> SP 87.5 %
#  16 MHz 1M:   BRP 0 (TQ 125 ns),  8 TQ = 1 + PRSEG 2 + PHSEG1 3 + PHSEG2 2 -> SP 75 %
#   8 MHz 500k: BRP 0 (TQ 250 ns),  8 TQ = 1 + PRSEG 2 + PHSEG1 3 + PHSEG2 2 -> SP 75 %
CNF = (
    (16000000, 500000, 0x00, 0xBC, 0x01),
    (16000000, 1000000, 0x00, 0x91, 0x01),
    (8000000, 500000, 0x00, 0x91, 0x01),
)


def cnf_for(xtal_hz, bitrate):
    # the (CNF1, CNF2, CNF3) tuple, or None
    for c in CNF:
        if c[0] == xtal_hz and c[1] == bitrate:
            return c[2], c[3], c[4]
    return None


def bit_ns(xtal_hz, cnf1, cnf2, cnf3):
    # nominal bit time (ns) the registers give
    tq = 2 * ((cnf1 & 0x3F) + 1) * 1000000000 // xtal_hz
    prseg = (cnf2 & 7) + 1
    ps1 = ((cnf2 >> 3) & 7) + 1
    ps2 = (cnf3 & 7) + 1
    return tq * (1 + prseg + ps1 + ps2)


class MCP2515:
    def __init__(self, spi, cs, irq=None):
        self.spi = spi
        self.cs = cs
        self.irq = irq
        self.tx = bytearray(16)
        self.rx = bytearray(16)
        mt = memoryview(self.tx)
        mr = memoryview(self.rx)
        self._tv = [mt[:k] for k in range(17)]
        self._rv = [mr[:k] for k in range(17)]
        self._wr = spi.write_readinto
        self._w = spi.write
        self._cs = cs.value
        self._irq = irq.value if irq is not None else None
        # READ RX BUFFER: its own receive buffer (the frame stays there until the next read_rx: a
        # link may hold a frame across ticks) and instruction buffers (the bytes after the
        # instruction are don't-care: left 0), so a read copies nothing in bytecode
        self._rxb = bytearray(14)
        self.rdata = memoryview(self._rxb)[6:14]
        self._rxq = (bytearray(14), bytearray(14))
        self._rxq[0][0] = _READ_RX
        self._rxq[1][0] = _READ_RX | (1 << 2)
        self.rid = 0
        self.rdlc = 0
        self.intf = 0
        self.eflg = 0
        self.tec = 0
        self.rec = 0
        self.node = 0
        self.cnf = None
        cs.value(1)

    # ---- SPI transactions (one CS-low window each) ----
    def _xfer(self, n):
        self._cs(0)
        self._wr(self._tv[n], self._rv[n])
        self._cs(1)

    def reset(self):
        self.tx[0] = _RESET
        self._xfer(1)

    def read(self, addr):
        t = self.tx
        t[0] = _READ
        t[1] = addr
        t[2] = 0
        self._xfer(3)
        return self.rx[2]

    def read_n(self, addr, n):
        # n consecutive registers into self.rx[2:2+n] (n <= 14)
        t = self.tx
        t[0] = _READ
        t[1] = addr
        for i in range(n):
            t[2 + i] = 0
        self._xfer(2 + n)

    def write(self, addr, v):
        t = self.tx
        t[0] = _WRITE
        t[1] = addr
        t[2] = v
        self._xfer(3)

    def write_n(self, addr, src, n):
        # src[0:n] into n consecutive registers (n <= 14)
        t = self.tx
        t[0] = _WRITE
        t[1] = addr
        for i in range(n):
            t[2 + i] = src[i]
        self._xfer(2 + n)

    def modify(self, addr, mask, v):
        t = self.tx
        t[0] = _MODIFY
        t[1] = addr
        t[2] = mask
        t[3] = v
        self._xfer(4)

    def status(self):
        # READ STATUS: RX0IF, RX1IF, TXB0 TXREQ, TX0IF, TXB1 TXREQ, TX1IF, TXB2 TXREQ, TX2IF
        t = self.tx
        t[0] = _STATUS
        t[1] = 0
        self._xfer(2)
        return self.rx[1]

    def rx_status(self):
        t = self.tx
        t[0] = _RXSTATUS
        t[1] = 0
        self._xfer(2)
        return self.rx[1]

    # ---- start-up ----
    def set_mode(self, mode):
        # request an operating mode; True once CANSTAT reports it (bounded polls)
        self.modify(R_CANCTRL, _MODE_MASK, mode)
        for _ in range(_TRIES):
            if self.read(R_CANSTAT) & _MODE_MASK == mode:
                return True
        return False

    def init(self, bitrate, xtal_hz, node, mode=MODE_NORMAL):
        cnf = cnf_for(xtal_hz, bitrate)
        if cnf is None:
            return E_BITRATE
        self.reset()
        # after RESET the chip restarts its oscillator (128 OSC cycles) and is in
        # configuration mode: CANSTAT 0x80.  A chip that is not there reads 0x00 or 0xFF
        ok = False
        for _ in range(_TRIES):
            if self.read(R_CANSTAT) & _MODE_MASK == MODE_CONFIG:
                ok = True
                break
        if not ok:
            return E_ABSENT
        b = bytearray(12)
        b[0] = cnf[2]       # CNF3
        b[1] = cnf[1]       # CNF2
        b[2] = cnf[0]       # CNF1
        b[3] = RX0IF | RX1IF | ERRIF | MERRF  # CANINTE
        b[4] = 0            # CANINTF
        self.write_n(R_CNF3, b, 5)
        self.read_n(R_CNF3, 4)
        r = self.rx
        if r[2] != b[0] or r[3] != b[1] or r[4] != b[2] or r[5] != b[3]:
            return E_ABSENT  # MISO/MOSI/SCK miswired: writes do not read back
        self.cnf = cnf
        self.node = node
        self.set_filters(node)
        # TX priorities: TXB0 highest (heartbeat, replies), TXB1, TXB2 (telemetry)
        self.write(R_TXB0CTRL, 3)
        self.write(R_TXB1CTRL, 2)
        self.write(R_TXB2CTRL, 1)
        # RXB0: filters on, rollover into RXB1; RXB1: filters on
        self.write(R_RXB0CTRL, 0x04)
        self.write(R_RXB1CTRL, 0x00)
        if not self.set_mode(mode):
            return E_MODE
        return OK

    def set_filters(self, node):
        # (configuration mode) masks 0x7E0 on both buffers, every filter node << 5, standard ids
        sid = (node & 0x3F) << 5
        b = bytearray(12)
        for i in range(3):
            b[4 * i] = sid >> 3
            b[4 * i + 1] = (sid & 7) << 5
        self.write_n(R_RXF0, b, 12)
        self.write_n(R_RXF3, b, 12)
        for i in range(2):
            b[4 * i] = 0x7E0 >> 3
            b[4 * i + 1] = (0x7E0 & 7) << 5
            b[4 * i + 2] = 0
            b[4 * i + 3] = 0
        self.write_n(R_RXM0, b, 8)

    # ---- running (allocation-free) ----
    def pending(self):
        # the INT pin is low (active): a flag in CANINTF wants service
        if self._irq is None:
            return True
        return self._irq() == 0

    def flags(self):
        # CANINTF and EFLG in one READ (consecutive registers)
        t = self.tx
        t[0] = _READ
        t[1] = R_CANINTF
        t[2] = 0
        t[3] = 0
        self._xfer(4)
        self.intf = self.rx[2]
        self.eflg = self.rx[3]

    def counters(self):
        t = self.tx
        t[0] = _READ
        t[1] = R_TEC
        t[2] = 0
        t[3] = 0
        self._xfer(4)
        self.tec = self.rx[2]
        self.rec = self.rx[3]

    def read_rx(self, k):
        # READ RX BUFFER k (0, 1): 13 bytes from SIDH; CS rising clears RXkIF.
        # -> standard id in rid (-1: extended or remote frame), dlc in rdlc, data in rdata (a view
        # of the read's own buffer: valid until the next read_rx)
        r = self._rxb
        self._cs(0)
        self._wr(self._rxq[k], r)
        self._cs(1)
        sidl = r[2]
        dlc = r[5]
        if sidl & 0x08 or sidl & 0x10 or dlc & 0x40:
            # IDE (extended), SRR (standard remote), RTR: not ours
            self.rid = -1
        else:
            self.rid = (r[1] << 3) | (sidl >> 5)
        self.rdlc = dlc & 0x0F

    def load_tx(self, k, buf, off):
        # LOAD TX BUFFER k (0..2) with buf[off:off+13]: SIDH SIDL EID8 EID0 DLC D0..D7
        t = self.tx
        t[0] = _LOAD_TX | (k << 1)
        for i in range(13):
            t[1 + i] = buf[off + i]
        self._xfer(14)

    def load_frame(self, k, frame):
        # LOAD TX BUFFER k from a 14-byte transaction buffer: frame[1:14] = SIDH SIDL EID8 EID0
        # DLC D0..D7 (frame[0] is set here): no copy
        frame[0] = _LOAD_TX | (k << 1)
        self._cs(0)
        self._w(frame)
        self._cs(1)

    def rts(self, mask):
        self.tx[0] = _RTS | (mask & 7)
        self._xfer(1)

    def tx_busy(self):
        # TXREQ of TXB0, TXB1, TXB2 as bits 0, 1, 2
        s = self.status()
        return ((s >> 2) & 1) | ((s >> 3) & 2) | ((s >> 4) & 4)

    def clear_errors(self):
        # ERRIF and MERRF acknowledged; receive overflow flags cleared
        self.modify(R_EFLG, RX0OVR | RX1OVR, 0)
        self.modify(R_CANINTF, ERRIF | MERRF, 0)

    def abort(self):
        # abort all pending transmissions (ABAT), then allow new ones again
        self.modify(R_CANCTRL, _ABAT, _ABAT)
        self.modify(R_CANCTRL, _ABAT, 0)
