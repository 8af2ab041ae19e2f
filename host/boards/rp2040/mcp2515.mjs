// MCP2515 stand-alone CAN controller on an rp2040js SPI peripheral, at the register level, and
// the CAN bus it sits on.  Used by harness.mjs (--mcp2515 '{"spi":1,"cs":13,"int":14,...}').
//
// SPI side: every byte the Pico clocks out (RPSPI.onTransmit) is answered after its 8 bit
// times at the SPI clock the firmware configured (an alarm on the simulation clock), as the
// chip shifts it.  A transaction is one CS-low window (CS is a GPIO output of the Pico, seen
// through its listener).  Instructions: RESET, READ, WRITE, BIT MODIFY, READ STATUS,
// RX STATUS, LOAD TX BUFFER (0x40 | abc), RTS (0x80 | nnn), READ RX BUFFER (0x90 | nm: the
// RXnIF is cleared when CS rises).  Registers: CANSTAT/CANCTRL (REQOP -> OPMOD, ABAT),
// CNF1-3, filters RXF0-5 and masks RXM0-1 (writable in configuration mode only, as on the
// chip), CANINTE/CANINTF, EFLG (RXnOVR writable), TEC/REC (read-only), TXBnCTRL (TXREQ, TXP;
// ABTF/MLOA/TXERR read-only), TXBn id/DLC/data, RXBnCTRL (RXM, BUKT; FILHIT read-only),
// RXBn (read-only).  The INT pin (a Pico GPIO input) is low while CANINTF & CANINTE != 0.
//
// Bus side: one bus shared by the chip and the outside nodes (frames queued by the Python side,
// each source a FIFO).  When the bus is idle the lowest identifier among the ready frames wins
// arbitration (inside the chip: highest TXP, then highest buffer number); a frame occupies the
// bus for its exact bit count -- SOF to CRC with stuff bits, CRC delimiter, ACK, EOF and the
// 3-bit intermission -- at the bit time the CNF registers give (TQ = 2 (BRP+1) / Fosc).  The
// chip receives outside frames through its acceptance filters (RXB0: RXM0 with RXF0-1, rolling
// over into RXB1 when BUKT is set; RXB1: RXM1 with RXF2-5) and flags overflows (RXnOVR).
//
// Errors: with the bus disturbed ({"cmd":"can_bus","error":true}) every transmission attempt
// ends in an error frame: the chip's own attempts raise TEC by 8 (and are retried, as with
// one-shot mode off), outside frames raise REC by 1 and are lost.  TEC/REC thresholds set
// EWARN/TXWAR/RXWAR (>= 96), TXEP/RXEP (>= 128) and TXBO (TEC > 255: bus-off, the chip neither
// sends nor receives); a change of the error state sets ERRIF.  A successful frame lowers its
// counter by one.  Bus-off recovery: after 128 x 11 recessive bits on an undisturbed bus the
// chip is error-active again with TEC = REC = 0.
const R = {
  CANSTAT: 0x0e, CANCTRL: 0x0f, TEC: 0x1c, REC: 0x1d, CNF3: 0x28, CNF2: 0x29, CNF1: 0x2a,
  CANINTE: 0x2b, CANINTF: 0x2c, EFLG: 0x2d, RXB0CTRL: 0x60, RXB1CTRL: 0x70,
};
const TXB = [0x30, 0x40, 0x50];
const RXB = [0x60, 0x70];
const FILTERS = [0x00, 0x04, 0x08, 0x10, 0x14, 0x18];
const MASKS = [0x20, 0x24];
const MODE_NORMAL = 0, MODE_SLEEP = 1, MODE_LOOPBACK = 2, MODE_LISTEN = 3, MODE_CONFIG = 4;
const RECOVERY_BITS = 128 * 11;
const ERROR_ATTEMPT_BITS = 40; // an errored attempt: some bits of the frame, the error flag and delimiter

function crc15(bits) {
  let crc = 0;
  for (const b of bits) {
    const nxt = b ^ ((crc >> 14) & 1);
    crc = (crc << 1) & 0x7fff;
    if (nxt) crc ^= 0x4599;
  }
  return crc;
}

// bits a classic standard data frame occupies on the bus, stuff bits and intermission included
export function frameBits(id, data) {
  const bits = [0];
  for (let i = 10; i >= 0; i--) bits.push((id >> i) & 1);
  bits.push(0, 0, 0); // RTR, IDE, r0
  const dlc = data.length;
  for (let i = 3; i >= 0; i--) bits.push((dlc >> i) & 1);
  for (const byte of data) for (let i = 7; i >= 0; i--) bits.push((byte >> i) & 1);
  const crc = crc15(bits);
  for (let i = 14; i >= 0; i--) bits.push((crc >> i) & 1);
  let stuffed = 0, run = 0, last = -1;
  for (const b of bits) {
    if (b === last) run++;
    else { run = 1; last = b; }
    if (run === 5) { stuffed++; last = 1 - b; run = 1; }
  }
  return bits.length + stuffed + 1 + 2 + 7 + 3; // CRC delim, ACK slot + delim, EOF, intermission
}

export class Mcp2515 {
  constructor({ mcu, clock, spi = 1, cs = 13, int: intPin = 14, xtal = 16000000, nsPerCycle = 8 }) {
    this.mcu = mcu;
    this.clock = clock;
    this.spi = mcu.spi[spi];
    this.csPin = cs;
    this.intPin = intPin;
    this.xtal = xtal;
    this.nsPerCycle = nsPerCycle;
    this.regs = new Uint8Array(128);
    this.txOut = []; // [cycle, id, hex] of frames the chip sent
    this.rxLost = 0; // outside frames lost (disturbed bus, chip off the bus)
    this.busFrames = 0; // frames completed on the bus (any sender)
    this.busBusyNs = 0; // time the bus carried frames
    this.spiBytes = 0;
    this.spiBusyNs = 0;
    this.transactions = 0;
    this.sources = new Map(); // name -> [{id, data, ready}]
    this.busUntil = 0;
    this.current = null;
    this.disturbed = false;
    this.busOff = false;
    this.quietSince = 0; // start of the undisturbed stretch counting towards bus-off recovery
    this.intLevel = null;
    // The chip drives its INT line: the harness's refresh of undriven pins from their pad pulls
    // (on every write to the pads) must not pull it back high while a flag is pending -- the
    // firmware then saw INT idle with RX0IF/RX1IF set and never read its buffers again.
    const pinObj = mcu.gpio[this.intPin];
    const setPin = pinObj.setInputValue.bind(pinObj);
    this.driveInt = setPin;
    pinObj.setInputValue = (v) => setPin(this.intLevel === null ? v : this.intLevel);
    this.byteAlarm = clock.createAlarm(() => this.byteDone());
    this.busAlarm = clock.createAlarm(() => this.busDone());
    this.recoverAlarm = clock.createAlarm(() => this.recover());
    this.pendingOut = 0;
    this.resetChip();
    this.spi.onTransmit = (v) => {
      this.pendingOut = this.shift(v & 0xff);
      this.spiBytes++;
      const hz = this.spi.clockFrequency || 1e6;
      const ns = (8 * 1e9) / hz;
      this.spiBusyNs += ns;
      this.byteAlarm.schedule(ns);
    };
    this.csLevel = 1;
    mcu.gpio[cs].addListener((value) => {
      const level = value === 0 ? 0 : 1;
      if (level === this.csLevel) return;
      this.csLevel = level;
      if (level === 0) { this.op = null; this.transactions++; } else this.endTransaction();
    });
  }

  // ------------------------------------------------------------ registers
  resetChip() {
    const r = this.regs;
    r.fill(0);
    r[R.CANSTAT] = 0x80;
    r[R.CANCTRL] = 0x87;
    this.op = null;
    this.busOff = false;
    this.recoverAlarm.cancel();
    this.updateInt();
  }
  get mode() { return (this.regs[R.CANSTAT] >> 5) & 7; }
  get onBus() { return !this.busOff && (this.mode === MODE_NORMAL || this.mode === MODE_LISTEN); }
  bitNs() {
    const r = this.regs;
    const brp = r[R.CNF1] & 0x3f;
    const tq = (2 * (brp + 1) * 1e9) / this.xtal;
    const prseg = (r[R.CNF2] & 7) + 1;
    const ps1 = ((r[R.CNF2] >> 3) & 7) + 1;
    const ps2 = r[R.CNF2] & 0x80 ? (r[R.CNF3] & 7) + 1 : Math.max(ps1, 2);
    return tq * (1 + prseg + ps1 + ps2);
  }
  read(a) {
    a &= 0x7f;
    if ((a & 0xf) === 0xe) return this.regs[R.CANSTAT]; // CANSTAT/CANCTRL appear at every 0xXE/0xXF
    if ((a & 0xf) === 0xf) return this.regs[R.CANCTRL];
    return this.regs[a];
  }
  write(a, v) {
    a &= 0x7f;
    const r = this.regs;
    const config = this.mode === MODE_CONFIG;
    if ((a & 0xf) === 0xe) return; // CANSTAT (read-only)
    if ((a & 0xf) === 0xf) { this.writeCanctrl(v); return; }
    if (a < 0x1c || (a >= 0x20 && a < 0x28)) { if (config) r[a] = v; return; } // filters, masks
    if (a === R.TEC || a === R.REC) return;
    if (a >= R.CNF3 && a <= R.CNF1) { if (config) r[a] = v; return; }
    if (a === R.CANINTE || a === R.CANINTF) { r[a] = v; this.updateInt(); return; }
    if (a === R.EFLG) { r[a] = (r[a] & 0x3f) | (r[a] & v & 0xc0); return; }
    for (let k = 0; k < 3; k++) {
      if (a === TXB[k]) {
        const was = r[a] & 0x08;
        r[a] = (r[a] & 0x70) | (v & 0x0b);
        if (v & 0x08) { r[a] &= ~0x40; if (!was) this.kick(); }
        return;
      }
      if (a > TXB[k] && a <= TXB[k] + 13) { r[a] = v; return; }
    }
    if (a === RXB[0]) { r[a] = (r[a] & 0x0b) | (v & 0x64); return; }
    if (a === RXB[1]) { r[a] = (r[a] & 0x0f) | (v & 0x60); return; }
    if (a === 0x0c || a === 0x0d) { r[a] = v; return; } // BFPCTRL, TXRTSCTRL
  }
  writeCanctrl(v) {
    const r = this.regs;
    const old = r[R.CANCTRL];
    r[R.CANCTRL] = v;
    if (v & 0x10 && !(old & 0x10)) this.abortAll();
    const req = (v >> 5) & 7;
    r[R.CANSTAT] = (r[R.CANSTAT] & 0x1f) | (req << 5);
    if (req === MODE_NORMAL || req === MODE_LISTEN) this.kick();
  }
  abortAll() {
    for (const a of TXB) {
      if (this.current && this.current.buf !== undefined && TXB[this.current.buf] === a) continue; // on the wire
      if (this.regs[a] & 0x08) this.regs[a] = (this.regs[a] & ~0x08) | 0x40; // ABTF
    }
  }
  modify(a, mask, v) {
    a &= 0x7f;
    const merged = (this.regs[a] & ~mask) | (v & mask);
    // BIT MODIFY works on the bit-modifiable registers; others take the whole byte (as the datasheet warns)
    this.write(a, merged & 0xff);
  }
  setFlag(bits) { this.regs[R.CANINTF] |= bits; this.updateInt(); }
  updateInt() {
    const low = (this.regs[R.CANINTF] & this.regs[R.CANINTE]) !== 0;
    const level = !low;
    if (level !== this.intLevel) {
      this.intLevel = level;
      this.driveInt(level);
    }
  }
  status() {
    const r = this.regs, f = r[R.CANINTF];
    return (f & 3) | ((r[TXB[0]] & 8) ? 4 : 0) | ((f & 4) ? 8 : 0) | ((r[TXB[1]] & 8) ? 16 : 0) |
      ((f & 8) ? 32 : 0) | ((r[TXB[2]] & 8) ? 64 : 0) | ((f & 16) ? 128 : 0);
  }
  rxStatus() {
    const r = this.regs, f = r[R.CANINTF] & 3;
    let v = f << 6;
    const k = f & 1 ? 0 : f & 2 ? 1 : -1;
    if (k >= 0) {
      const b = RXB[k];
      if (r[b + 2] & 0x08) v |= 0x10;
      if (r[b + 5] & 0x40) v |= 0x08;
      v |= k === 0 ? r[b] & 1 : r[b] & 7;
    }
    return v;
  }

  // ------------------------------------------------------------ SPI
  shift(v) {
    // one byte of the current transaction: returns what the chip shifts out meanwhile
    if (this.csLevel !== 0) return 0xff; // not selected: MISO high-impedance (pulled up)
    const op = this.op;
    if (op === null) {
      this.op = { code: v, n: 0, addr: 0 };
      if (v === 0xc0) this.resetChip();
      else if ((v & 0xf8) === 0x40 && (v & 7) < 6) { this.op.addr = TXB[v >> 1 & 3] + (v & 1 ? 6 : 1); this.op.kind = 'load'; }
      else if ((v & 0xf8) === 0x80) {
        for (let k = 0; k < 3; k++) if (v & (1 << k)) this.write(TXB[k], this.regs[TXB[k]] | 0x08);
      } else if ((v & 0xf9) === 0x90) { this.op.addr = RXB[(v >> 2) & 1] + (v & 2 ? 6 : 1); this.op.kind = 'rx'; this.op.buf = (v >> 2) & 1; }
      return 0;
    }
    op.n++;
    switch (op.code) {
      case 0x03: // READ
        if (op.n === 1) { op.addr = v; return 0; }
        return this.read(op.addr++);
      case 0x02: // WRITE
        if (op.n === 1) { op.addr = v; return 0; }
        this.write(op.addr++, v);
        return 0;
      case 0x05: // BIT MODIFY
        if (op.n === 1) op.addr = v;
        else if (op.n === 2) op.mask = v;
        else if (op.n === 3) this.modify(op.addr, op.mask, v);
        return 0;
      case 0xa0: return this.status();
      case 0xb0: return this.rxStatus();
    }
    if (op.kind === 'load') {
      const base = TXB[(op.code >> 1) & 3];
      if (op.addr <= base + 13) this.regs[op.addr] = v;
      op.addr++;
      return 0;
    }
    if (op.kind === 'rx') {
      const base = RXB[op.buf];
      const out = op.addr <= base + 13 ? this.regs[op.addr] : 0;
      op.addr++;
      return out;
    }
    return 0;
  }
  byteDone() { this.spi.completeTransmit(this.pendingOut); }
  endTransaction() {
    const op = this.op;
    this.op = null;
    if (op && op.kind === 'rx') {
      this.regs[R.CANINTF] &= ~(1 << op.buf);
      this.updateInt();
    }
  }

  // ------------------------------------------------------------ bus
  queue(source, id, data) {
    if (!this.sources.has(source)) this.sources.set(source, []);
    this.sources.get(source).push({ id, data: Uint8Array.from(data), ready: this.clock.nanos });
    this.kick();
  }
  chipCandidate() {
    if (!this.onBus || this.mode === MODE_LISTEN) return null;
    let best = -1, bestP = -1;
    for (let k = 0; k < 3; k++) {
      const c = this.regs[TXB[k]];
      if (c & 0x08 && (c & 3) >= bestP) { best = k; bestP = c & 3; }
    }
    if (best < 0) return null;
    const b = TXB[best], r = this.regs;
    const id = (r[b + 1] << 3) | (r[b + 2] >> 5);
    const n = Math.min(8, r[b + 5] & 0x0f);
    return { id, data: r.slice(b + 6, b + 6 + n), buf: best };
  }
  kick() {
    // start the next frame if the bus is idle
    if (this.current) return;
    const now = this.clock.nanos;
    if (now < this.busUntil) { this.busAlarm.schedule(this.busUntil - now); return; }
    let win = this.chipCandidate();
    for (const [name, q] of this.sources) {
      if (q.length && q[0].ready <= now && (win === null || q[0].id < win.id)) win = { ...q[0], source: name };
    }
    if (win === null) return;
    const bits = this.disturbed ? ERROR_ATTEMPT_BITS : frameBits(win.id, win.data);
    const ns = bits * this.bitNs();
    win.start = now;
    win.bits = bits;
    this.current = win;
    this.busAlarm.schedule(ns);
  }
  busDone() {
    const f = this.current;
    if (!f) { this.kick(); return; }
    this.current = null;
    const now = this.clock.nanos;
    this.busUntil = now;
    const r = this.regs;
    if (this.disturbed) {
      if (f.buf !== undefined) {
        this.setCounters(r[R.TEC] + 8, r[R.REC]);
      } else {
        this.sources.get(f.source).shift();
        this.rxLost++;
        if (this.onBus) this.setCounters(r[R.TEC], r[R.REC] + 1);
      }
    } else {
      this.busFrames++;
      this.busBusyNs += now - f.start;
      if (f.buf !== undefined) {
        const b = TXB[f.buf];
        r[b] &= ~0x08;
        this.txOut.push([Math.round(now / this.nsPerCycle), f.id, Buffer.from(f.data).toString('hex')]);
        this.setCounters(Math.max(0, r[R.TEC] - 1), r[R.REC]);
        this.setFlag(4 << f.buf);
      } else {
        this.sources.get(f.source).shift();
        if (this.onBus) {
          const rec = r[R.REC];
          this.setCounters(r[R.TEC], rec > 127 ? 119 : Math.max(0, rec - 1));
          this.receive(f.id, f.data);
        } else this.rxLost++;
      }
    }
    this.kick();
  }
  setCounters(tec, rec) {
    const r = this.regs;
    const before = r[R.EFLG] & 0x3f;
    if (tec > 255) {
      if (!this.busOff) {
        this.busOff = true;
        this.busOffCount = (this.busOffCount || 0) + 1;
        this.quietSince = this.clock.nanos;
        this.scheduleRecovery();
      }
      tec = 255;
    }
    r[R.TEC] = Math.max(0, Math.min(255, tec));
    r[R.REC] = Math.max(0, Math.min(255, rec));
    const t = r[R.TEC], c = r[R.REC];
    let e = 0;
    if (t >= 96 || c >= 96) e |= 1;
    if (c >= 96) e |= 2;
    if (t >= 96) e |= 4;
    if (c >= 128) e |= 8;
    if (t >= 128 && !this.busOff) e |= 16;
    if (this.busOff) e |= 32;
    r[R.EFLG] = (r[R.EFLG] & 0xc0) | e;
    if (e !== before) this.setFlag(0x20);
  }
  scheduleRecovery() {
    if (!this.busOff) return;
    if (this.disturbed) { this.recoverAlarm.cancel(); return; }
    const due = this.quietSince + RECOVERY_BITS * this.bitNs();
    this.recoverAlarm.schedule(Math.max(0, due - this.clock.nanos));
  }
  recover() {
    if (!this.busOff || this.disturbed) return;
    this.busOff = false;
    this.setCounters(0, 0);
    this.kick();
  }
  setDisturbed(on) {
    if (on === this.disturbed) return;
    this.disturbed = on;
    if (!on) { this.quietSince = this.clock.nanos; this.scheduleRecovery(); } else this.recoverAlarm.cancel();
    this.kick();
  }
  match(k, id) {
    const r = this.regs;
    const m = MASKS[k];
    const mask = (r[m] << 3) | (r[m + 1] >> 5);
    const list = k === 0 ? [0, 1] : [2, 3, 4, 5];
    for (const i of list) {
      const f = FILTERS[i];
      if (r[f + 1] & 0x08) continue; // EXIDE: extended-only filter
      const fid = (r[f] << 3) | (r[f + 1] >> 5);
      if (((fid ^ id) & mask) === 0) return i;
    }
    return -1;
  }
  receive(id, data) {
    const r = this.regs;
    const rxm0 = (r[RXB[0]] >> 5) & 3, rxm1 = (r[RXB[1]] >> 5) & 3;
    const f = r[R.CANINTF];
    let hit0 = rxm0 === 3 ? 0 : this.match(0, id);
    if (hit0 >= 0) {
      if (!(f & 1)) { this.store(0, id, data, hit0); return; }
      if (r[RXB[0]] & 0x04) { // BUKT: roll over into RXB1
        if (!(f & 2)) { this.store(1, id, data, hit0); r[RXB[0]] |= 0x02; return; }
        this.overflow(0x80);
        return;
      }
      this.overflow(0x40);
      return;
    }
    const hit1 = rxm1 === 3 ? 0 : this.match(1, id);
    if (hit1 < 0) return; // not for this node
    if (!(f & 2)) this.store(1, id, data, hit1);
    else this.overflow(0x80);
  }
  store(k, id, data, hit) {
    const r = this.regs, b = RXB[k];
    r[b + 1] = id >> 3;
    r[b + 2] = (id & 7) << 5;
    r[b + 3] = 0;
    r[b + 4] = 0;
    r[b + 5] = data.length;
    for (let i = 0; i < 8; i++) r[b + 6 + i] = i < data.length ? data[i] : 0;
    if (k === 0) r[b] = (r[b] & ~0x03) | (hit & 1);
    else r[b] = (r[b] & ~0x07) | (hit & 7);
    this.setFlag(1 << k);
  }
  overflow(bit) {
    this.regs[R.EFLG] |= bit;
    this.rxOverflows = (this.rxOverflows || 0) + 1;
    this.setFlag(0x20);
  }

  // ------------------------------------------------------------ Python side
  drainTx() { const t = this.txOut; this.txOut = []; return t; }
  summary() {
    const r = this.regs;
    return {
      mode: this.mode, tec: r[R.TEC], rec: r[R.REC], eflg: r[R.EFLG], canintf: r[R.CANINTF],
      cnf: [r[R.CNF1], r[R.CNF2], r[R.CNF3]], bit_ns: this.bitNs(), bus_off: this.busOff,
      bus_off_count: this.busOffCount || 0, rx_lost: this.rxLost, rx_overflows: this.rxOverflows || 0,
      bus_frames: this.busFrames, bus_busy_ns: this.busBusyNs, spi_bytes: this.spiBytes,
      spi_busy_ns: this.spiBusyNs, transactions: this.transactions, int_level: this.intLevel ? 1 : 0,
      queued: [...this.sources.values()].reduce((s, q) => s + q.length, 0),
    };
  }
}
