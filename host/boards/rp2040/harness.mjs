// Emulated RP2040 (rp2040js 1.4.1) running a MicroPython image, driven in lock-step by a parent
// process over stdin/stdout (JSON lines).  Used by host/boards/rp2040/board.py (EmulatedBoard).
//
//   node harness.mjs --bootrom B.bin --firmware firmware.bin [--fs fs.img --fs-offset 0xA0000]
//                    [--xip-cache on|off] [--xip-miss CYCLES]   (the XIP flash cache model, below)
//
// Requests (one JSON object a line; every request gets exactly one JSON answer line):
//   {"cmd":"adc","ch":0,"value":2048,"open":false}  ADC input channel (12-bit value); open: the
//                                           pin floats there (pad pulls then win, see below)
//   {"cmd":"encoder","count":N,"within_us":W}  quadrature position target (x4 counts, A=GP2
//                                           B=GP3): reached by edges spread evenly over the next
//                                           "run" (or over its first W us when given),
//                                           never closer than 0.25 us (ENC_GAP_NS: a larger
//                                           jump goes on into the following runs)
//   {"cmd":"uart","data":"<hex>"}           bytes onto UART0 RX, one after another at the line's
//                                           byte time (start + data + parity + stop bits at the
//                                           baud rate the firmware configured)
//   {"cmd":"usb","data":"<hex>"}            bytes from the USB host to the CDC OUT endpoint
//   {"cmd":"run","us":1000}                 run for that much emulated time; answers the state
//   {"cmd":"state"}                         the state answer without running
//   {"cmd":"config","pwm":16,"dir":17,"en":18,"watch":[17,18],"pwm_edges":false,"pio_exact":false,
//    "loop_probe":{"gap_us":40,"min_reads":3,"raw":false}}
//                                           pio_exact: step every state machine after every CPU
//                                           instruction with no skips (the reference the fast
//                                           stepping below must match; slow)
//                                           loop_probe: find the firmware's loop iterations from
//                                           its reads of the TIMER (see "loop probe" below);
//                                           null switches it off
//   {"cmd":"power_cut","op":K,"keep":M}     the K-th flash erase/program from now does only its
//                                           first M bytes, then the core stops (see "flash
//                                           programming"); "op":null disarms
//   {"cmd":"flash","offset":O,"length":L}   read the flash array (base64 "data")
//   {"cmd":"flash_log","on":true}           log flash operations from now; answers the log so far
//   {"cmd":"xip","on":true,"miss":64,"flush":false}  switch the XIP cache model, change its miss
//                                           penalty, flush it; answers its state ("xip", also in
//                                           every run/state answer)
//   {"cmd":"quit"}
// Answers: {"ok":true,...} or {"ok":false,"error":"..."}.  A "run" answer holds the cycle count,
// the PWM slice of the PWM pin (raw registers and the double-buffered values in force), DIR/EN
// levels, pin edges and PWM register writes with their cycle times, the bytes written to UART0 TX
// (with completion cycles) and to USB CDC, the UART baud rate, and whether the core halted.
//
// Three rp2040js defects are worked around at run time (the package is not forked):
//  1. USB CDC: the host model answered every armed OUT endpoint at once (a zero-length packet when
//     it had nothing to send): an interrupt storm.  Here an OUT transfer is held until data is
//     there, as a real host does.
//  2. UART: the TX interrupt was re-asserted on every interrupt check and TX was instantaneous.
//     Here the PL011 is modelled: a 32-byte TX FIFO (1 with FIFOs off) feeding a shift register
//     that takes one character time a byte; TXFF/TXFE/BUSY flags; the TX interrupt asserted when
//     the FIFO level falls through the IFLS trigger level (a transition, as the PL011 does); the RX
//     interrupt at the RX trigger level plus the receive timeout (32 bit times after the last byte).
//  3. PIO: was stepped from a wall-clock timer.  Here every enabled state machine is stepped in
//     lock-step with the CPU's cycle count, honouring its clock divider and instruction delays.
import { readFileSync } from 'node:fs';
import { createInterface } from 'node:readline';
import { BasePeripheral, RP2040, USBCDC } from 'rp2040js';
import { Mcp2515 } from './mcp2515.mjs';

const args = {};
for (let i = 2; i < process.argv.length; i += 2) {
  args[process.argv[i].replace(/^--/, '')] = process.argv[i + 1];
}

const NS_PER_CYCLE = 8; // 125 MHz, as the rp2040js Simulator assumes
const LOG_KEEP = 40;

// ---------------------------------------------------------------- logger (never to stdout)
const logTail = [];
let logCount = 0;
function logMsg(level, comp, msg) {
  logCount++;
  if (logTail.length >= LOG_KEEP) logTail.shift();
  logTail.push(`${level} [${comp}] ${msg}`);
}
const logger = {
  debug() {},
  info() {},
  warn(c, m) { logMsg('W', c, m); },
  error(c, m) { logMsg('E', c, m); },
};

// ---------------------------------------------------------------- the chip
const mcu = new RP2040();
mcu.logger = logger;
// VREG_AND_CHIP_RESET is unimplemented in rp2040js: its reads return 0xffffffff, and the B1
// bootrom then sees CHIP_RESET.PSM_RESTART_FLAG (a debugger-requested restart) and sleeps forever
// in its WFI loop.  Serve the registers with their power-on values (CHIP_RESET: HAD_POR).
class VregChipReset extends BasePeripheral {
  constructor(rp2040, name) {
    super(rp2040, name);
    this.regs = [0xb1, 0x91, 0x100];
  }
  readUint32(offset) { return offset < 12 ? this.regs[offset >> 2] : 0; }
  writeUint32(offset, value) {
    if (offset === 8) this.regs[2] &= ~(value & 0x1000000); // PSM_RESTART_FLAG is write-1-to-clear
    else if (offset < 8) this.regs[offset >> 2] = value;
  }
}
mcu.peripherals[0x40064] = new VregChipReset(mcu, 'VREG_AND_CHIP_RESET_BASE');
// BOOTSEL: the bootrom samples QSPI_SS (SIO GPIO_HI_IN bit 1) and enters USB boot when it reads
// low.  On a Pico the flash's chip select idles high (pad pull-up, input enabled at reset: 0x5a);
// rp2040js leaves it low with the input disabled, i.e. the button pressed.
mcu.qspi[1].padValue = 0x5a;
mcu.qspi[1].setInputValue(true);
const { core } = mcu;
const clock = mcu.clock;
{
  const rom = readFileSync(args.bootrom);
  if (rom.length !== 16384) throw new Error(`bootrom must be 16384 bytes, got ${rom.length}`);
  mcu.loadBootrom(new Uint32Array(rom.buffer, rom.byteOffset, 4096));
  const fw = readFileSync(args.firmware);
  mcu.flash.set(fw, 0);
  if (args.fs) {
    const fs = readFileSync(args.fs);
    mcu.flash.set(fs, Number(args['fs-offset'] ?? 0xa0000));
  }
  core.reset();
  // The bootrom's own flash boot reads boot2 through the SSI in serial mode, which rp2040js does
  // not model (it would read zeros, fail the CRC and fall into USB boot).  Start where the bootrom
  // would jump after a good CRC: boot2 at the start of flash (XIP reads are served from the flash
  // array), which then enters the image through its vector table.  The bootrom stays mapped for
  // its ROM functions (memcpy, flash routines, lookup tables).
  core.PC = 0x10000000;
}

let cyc = 0; // emulated cycles since reset (clock.nanos = cyc * 8)
let halted = false;
let breakCode = null;
let idleCycles = 0; // cycles spent in WFI/WFE
mcu.onBreak = (code) => {
  if (romServe(code)) return; // a bootrom flash routine, served on the flash array (below)
  halted = true;
  breakCode = code;
};

function setNanos(n) {
  // Advance the simulation clock to n (firing due alarms); cheap when none is due.
  const next = clock.nextAlarm;
  if (next !== null && next.nanos <= n) clock.tick(n - clock.nanosCounter);
  else clock.nanosCounter = n;
}

// ---------------------------------------------------------------- 3. lock-step PIO
// rp2040js runs PIO from setTimeout (1000 steps per macrotask, no divider).  That is disabled;
// every enabled state machine is stepped at its own clock-enable times on the CPU's cycle count:
// one step per divider period (int + frac/256 system cycles), 1 + delay periods per instruction,
// one period per stalled cycle.  Several machines are interleaved in time order.
//
// Speed, without giving up exactness:
//  * Lazy stepping: while no PIO interrupt is enabled and no DMA channel is busy, nothing on the
//    chip can see a state machine's state except through its registers: rp2040js feeds a PIO
//    output pin back into nothing (not GPIO_IN, not a GPIO interrupt, not another block's `in`),
//    so its level is seen only by the harness's pin listeners and state answers.  The machines are
//    then caught up to the current cycle just before the CPU touches a PIO or IO_BANK0 register,
//    before an input pin or the IO/pad configuration changes, and at the end of each run -- the
//    same steps at the same cycles as stepping after every instruction; a pin a machine drives
//    changes (and its listeners see the edge) at the cycle of the instruction that drove it.
//    Otherwise they are stepped after every CPU instruction (and cycle by cycle in WFI).
//  * Stalled on an empty TX FIFO (`pull block`, an autopull `out`): nothing but a register write
//    (the CPU, or a DMA channel through the same bus) can end the stall, and every register access
//    catches the machines up first: the stalled clock periods are skipped in one go.
//  * Steady state: a machine whose complete state (registers, shift counters, FIFO contents, IRQ
//    flags, its block's pins) is identical at two consecutive passes through its wrap target,
//    with nothing external touching it in between, repeats that period; whole periods are skipped
//    by advancing its clock-enable time (its state is then the one it would have) -- up to the
//    next step of any other machine (which could change what it sees).  The quadrature decoder
//    idles like that (it pushes an unchanged count into a full FIFO).
const pioSMs = []; // {sm, pio, next, div, snap, snapAt, same, period}
let pioNext = Infinity;
let pioLazy = false;
let pioSkipped = 0; // PIO cycles skipped by the steady-state and stall rules (statistics)
let pioExact = false; // config "pio_exact": every machine stepped after every instruction, no skips (reference)
const WAIT_TX = 3, WAIT_OUT = 5; // rp2040js WaitType.txFIFO, WaitType.Out
function smDiv(sm) {
  const i = sm.clockDivInt === 0 ? 65536 : sm.clockDivInt;
  return i + sm.clockDivFrac / 256;
}
function pioCanWake() {
  for (const pio of mcu.pio) {
    if (pio.irq0IntEnable | pio.irq0IntForce | pio.irq1IntEnable | pio.irq1IntForce) return true;
  }
  // a busy DMA channel (it could be paced by a PIO DREQ and raise an interrupt)
  for (const ch of mcu.dma.channels) if (ch.ctrl & (1 << 24)) return true;
  return false;
}
function pioMode() {
  pioLazy = !pioExact && pioSMs.length > 0 && !pioCanWake();
}
function refreshPio() {
  const old = new Map(pioSMs.map((e) => [e.sm, e]));
  pioSMs.length = 0;
  for (const pio of mcu.pio) {
    for (const sm of pio.machines) {
      if (!sm.enabled) continue;
      const div = smDiv(sm);
      const prev = old.get(sm);
      pioSMs.push({ sm, pio, div, next: prev ? prev.next : cyc + div, snap: null, snapAt: 0, same: false, period: 0 });
    }
  }
  pioNext = Infinity;
  for (const e of pioSMs) if (e.next < pioNext) pioNext = e.next;
  pioMode();
}
function pioTouched() {
  for (let k = 0; k < pioSMs.length; k++) {
    pioSMs[k].snap = null;
    pioSMs[k].same = false;
  }
}
function pioCatchUp() {
  // step the machines up to the current time (before something observes their pins)
  if (pioSMs.length) {
    const now = Math.floor(clock.nanosCounter / NS_PER_CYCLE);
    if (pioNext <= now) stepPio(now);
  }
}
function pioSync() {
  // catch the machines up to the current time (before something observes or changes their world)
  pioCatchUp();
  pioTouched();
}
function smSnapshot(sm, pio) {
  const rx = sm.rxFIFO, tx = sm.txFIFO;
  return `${sm.pc},${sm.x},${sm.y},${sm.inputShiftReg},${sm.inputShiftCount},${sm.outputShiftReg},` +
    `${sm.outputShiftCount},${sm.waiting},${sm.waitType},${sm.execValid},${sm.execCtrl},${rx.items},` +
    `${tx.items},${pio.irq},${pio.pinValues},${pio.pinDirections}`;
}
function pinsAt(pio, at) {
  // a machine changed its block's pins: the GPIO listeners see it at the cycle it happened
  const now = clock.nanosCounter;
  clock.nanosCounter = at * NS_PER_CYCLE;
  pio.checkChangedPins();
  clock.nanosCounter = now;
}
function stepPio(upTo) {
  const n = pioSMs.length;
  for (;;) {
    // the machine due first (time order: machines of one block talk through IRQ flags)
    let e = null;
    for (let k = 0; k < n; k++) {
      const c = pioSMs[k];
      if (c.next <= upTo && (e === null || c.next < e.next)) e = c;
    }
    if (e === null) break;
    const sm = e.sm;
    if (pioExact) {
      // the reference: no skips
    } else if (sm.waiting && !sm.execValid && (sm.waitType === WAIT_TX || sm.waitType === WAIT_OUT) && sm.txFIFO.empty) {
      const k = Math.floor((upTo - e.next) / e.div) + 1;
      e.next += k * e.div;
      pioSkipped += k * e.div;
      continue;
    } else if (sm.pc === sm.wrapBottom && !sm.waiting) {
      if (!e.same) {
        const snap = smSnapshot(sm, e.pio);
        if (snap === e.snap && e.next > e.snapAt) {
          e.same = true;
          e.period = e.next - e.snapAt;
        } else {
          e.snap = snap;
          e.snapAt = e.next;
        }
      }
      if (e.same) {
        // whole periods, up to the next step of another machine
        let limit = upTo;
        for (let k = 0; k < n; k++) if (pioSMs[k] !== e && pioSMs[k].next < limit) limit = pioSMs[k].next;
        const j = Math.floor((limit - e.next) / e.period);
        if (j > 0) {
          e.next += j * e.period;
          pioSkipped += j * e.period;
          continue;
        }
        // no whole period before another machine's step: on, and compare again at the next wrap
        e.same = false;
        e.snapAt = e.next;
      }
    }
    const pio = e.pio;
    const irq = pio.irq, pv = pio.pinValues, pd = pio.pinDirections;
    const at = e.next;
    const c0 = sm.cycles;
    sm.step();
    let dc = sm.cycles - c0; // 1 + delay, 0 while stalled
    if (dc < 1) dc = 1;
    e.next += dc * e.div;
    if (pio.irq !== irq || pio.pinValues !== pv || pio.pinDirections !== pd) {
      // what the block's other machines see changed: their steady state is to be seen again
      for (let k = 0; k < n; k++) if (pioSMs[k].pio === pio) pioSMs[k].same = false;
      if (pio.pinValues !== pio.oldPinValues || pio.pinDirections !== pio.oldPinDirections) pinsAt(pio, at);
    }
  }
  let next = Infinity;
  for (let k = 0; k < n; k++) if (pioSMs[k].next < next) next = pioSMs[k].next;
  pioNext = next;
}
for (const pio of mcu.pio) {
  pio.run = () => {}; // no wall-clock stepping
  const origWrite = pio.writeUint32.bind(pio);
  const origRead = pio.readUint32.bind(pio);
  pio.readUint32 = (offset) => {
    pioSync();
    return origRead(offset);
  };
  pio.writeUint32 = (offset, value) => {
    pioSync();
    origWrite(offset, value);
    pio.checkChangedPins(); // an SMn_INSTR write (pio_sm_set_pins...) drives pins now
    // CTRL (enable/restart) and SMn_CLKDIV (0xc8 + 0x18 n) change the stepping plan
    if (offset === 0 || (offset >= 0xc8 && offset <= 0x124 && (offset - 0xc8) % 0x18 === 0)) refreshPio();
    else pioMode();
  };
}
{
  const origWrite = mcu.dma.writeUint32.bind(mcu.dma);
  mcu.dma.writeUint32 = (offset, value) => {
    pioSync();
    origWrite(offset, value);
    pioMode();
  };
}

// ---------------------------------------------------------------- fast GPIO input word
// RP2040.gpioValues (read by every PIO `in pins`/`wait`/`mov x, pins`) walks all 30 pins through
// getters.  Cache it; the cache is dropped when an input level, IO_BANK0 (overrides) or
// PADS_BANK0 (input enable) changes -- after catching the PIO up to that moment.
let gpioCache = -1;
Object.defineProperty(mcu, 'gpioValues', {
  get() {
    if (gpioCache < 0) {
      let v = 0;
      const { gpio } = mcu;
      for (let i = 0; i < gpio.length; i++) if (gpio[i].inputValue) v |= 1 << i;
      gpioCache = v >>> 0;
    }
    return gpioCache;
  },
});
for (const pin of mcu.gpio) {
  const orig = pin.setInputValue.bind(pin);
  pin.setInputValue = (value) => { pioSync(); gpioCache = -1; orig(value); };
}
// A digital input nothing outside drives follows its pad pull (rp2040js reads it as 0 whatever
// the pull): e.g. the e-stop input, pulled up, reads 1 until the harness drives it ("pin").
// Pins the harness drives (the encoder, "pin") are left alone.
const drivenPins = new Set([2, 3]);
function followPulls() {
  for (const pin of mcu.gpio) {
    if (drivenPins.has(pin.index)) continue;
    const v = pin.pullupEnabled && !pin.pulldownEnabled;
    if (pin.rawInputValue !== v) pin.setInputValue(v);
  }
}
for (const base of [0x40014, 0x4001c]) {
  const per = mcu.peripherals[base];
  const orig = per.writeUint32.bind(per);
  per.writeUint32 = (offset, value) => {
    pioSync();
    gpioCache = -1;
    orig(offset, value);
    if (base === 0x4001c) followPulls();
  };
}
{
  // IO_BANK0 GPIOn_STATUS shows a pin's output (a PIO's too): the machines catch up first
  const per = mcu.peripherals[0x40014];
  const orig = per.readUint32.bind(per);
  per.readUint32 = (offset) => {
    pioCatchUp();
    return orig(offset);
  };
}

// ---------------------------------------------------------------- 2. UART (PL011 model)
const UARTDR = 0x0, UARTFR = 0x18, UARTLCR_H = 0x2c, UARTIFLS = 0x34, UARTIMSC = 0x38, UARTICR = 0x44;
const TXINTR = 1 << 5, RXINTR = 1 << 4, RTINTR = 1 << 6, OEINTR = 1 << 10;
const FIFO_LEVELS = [4, 8, 16, 24, 28];
class UartModel {
  constructor(u) {
    this.u = u;
    this.ifls = 0x12;
    this.txFifo = [];
    this.txBusy = false;
    this.txOut = []; // [byte, completion cycle]
    this.overruns = 0;
    this.baud = 0;
    this.rxQueue = []; // bytes still on the line
    this.rxLineBusy = false;
    this.txAlarm = clock.createAlarm(() => this.txDone());
    this.rxAlarm = clock.createAlarm(() => this.rxArrive());
    this.rtAlarm = clock.createAlarm(() => this.rxTimeout());
    this.shifting = 0;
    u.onBaudRateChange = (b) => { this.baud = b; };
    u.checkInterrupts = () => this.irq();
    u.feedByte = (b) => this.rxPush(b);
    const origRead = u.readUint32.bind(u);
    const origWrite = u.writeUint32.bind(u);
    u.readUint32 = (offset) => {
      switch (offset) {
        case UARTDR: return this.rxPull();
        case UARTFR: return this.flags();
        case UARTIFLS: return this.ifls;
      }
      return origRead(offset);
    };
    u.writeUint32 = (offset, value) => {
      switch (offset) {
        case UARTDR: this.txPush(value & 0xff); return;
        case UARTIFLS: this.ifls = value & 0x3f; return;
        case UARTICR: u.interruptStatus &= ~u.rawWriteValue; this.irq(); return;
        case UARTIMSC: u.interruptMask = value & 0x7ff; this.irq(); return;
      }
      origWrite(offset, value);
    };
  }
  get depth() { return this.u.fifosEnabled ? 32 : 1; }
  get txTrigger() { return this.u.fifosEnabled ? FIFO_LEVELS[this.ifls & 7] ?? 16 : 0; }
  get rxTrigger() { return this.u.fifosEnabled ? FIFO_LEVELS[(this.ifls >> 3) & 7] ?? 16 : 1; }
  get exactBaud() {
    const d = this.u.baudDivider;
    return d ? mcu.clkPeri / (16 * d) : 115200;
  }
  get charNanos() {
    const lcr = this.u.lineCtrlRegister;
    const bits = 1 + this.u.wordLength + (lcr & 2 ? 1 : 0) + (lcr & 8 ? 2 : 1);
    return (bits * 1e9) / this.exactBaud;
  }
  irq() {
    const u = this.u;
    mcu.setInterrupt(u.irq, !!(u.interruptStatus & u.interruptMask));
  }
  flags() {
    const u = this.u;
    const rx = u.rxFIFO;
    return (
      (this.txBusy || this.txFifo.length ? 1 << 3 : 0) |
      (rx.empty ? 1 << 4 : 0) |
      (this.txFifo.length >= this.depth ? 1 << 5 : 0) |
      (rx.itemCount >= this.depthRx() ? 1 << 6 : 0) |
      (this.txFifo.length === 0 ? 1 << 7 : 0)
    );
  }
  depthRx() { return this.depth; }
  txPush(b) {
    if (this.txFifo.length >= this.depth) return; // written while full: lost, as on the PL011
    this.txFifo.push(b);
    if (this.txFifo.length > this.txTrigger) this.u.interruptStatus &= ~TXINTR;
    if (!this.txBusy) this.txStart();
    this.irq();
  }
  txStart() {
    const before = this.txFifo.length;
    this.shifting = this.txFifo.shift();
    this.txBusy = true;
    this.txAlarm.schedule(this.charNanos);
    if (before > this.txTrigger && this.txFifo.length <= this.txTrigger) {
      this.u.interruptStatus |= TXINTR;
      this.irq();
    }
  }
  txDone() {
    this.txOut.push(this.shifting, Math.round(clock.nanos / NS_PER_CYCLE));
    this.txBusy = false;
    if (this.txFifo.length) this.txStart();
  }
  // RX: bytes arrive one character time apart; the FIFO holds 32 (1 with FIFOs off)
  queueRx(bytes) {
    for (const b of bytes) this.rxQueue.push(b);
    if (!this.rxLineBusy && this.rxQueue.length) {
      this.rxLineBusy = true;
      this.rxAlarm.schedule(this.charNanos);
    }
  }
  rxArrive() {
    this.rxPush(this.rxQueue.shift());
    if (this.rxQueue.length) this.rxAlarm.schedule(this.charNanos);
    else this.rxLineBusy = false;
  }
  rxPush(b) {
    const u = this.u;
    if (u.rxFIFO.itemCount >= this.depthRx()) {
      this.overruns++;
      u.interruptStatus |= OEINTR;
    } else {
      u.rxFIFO.push(b);
      if (u.rxFIFO.itemCount >= this.rxTrigger) u.interruptStatus |= RXINTR;
    }
    this.rtAlarm.schedule((32 * 1e9) / this.exactBaud);
    this.irq();
  }
  rxTimeout() {
    if (!this.u.rxFIFO.empty) {
      this.u.interruptStatus |= RTINTR;
      this.irq();
    }
  }
  rxPull() {
    const u = this.u;
    const v = u.rxFIFO.pull();
    if (u.rxFIFO.itemCount < this.rxTrigger) u.interruptStatus &= ~RXINTR;
    if (u.rxFIFO.empty) u.interruptStatus &= ~RTINTR;
    this.irq();
    return v;
  }
}
const uarts = mcu.uart.map((u) => new UartModel(u));

// ---------------------------------------------------------------- 1. USB CDC
const cdc = new USBCDC(mcu.usbCtrl);
const usbIn = []; // host -> device bytes not yet taken
let usbPending = null; // [endpoint, size] of an OUT transfer the device armed
const usbOut = []; // device -> host bytes
let usbConnected = false;
cdc.onDeviceConnected = () => { usbConnected = true; };
cdc.onSerialData = (buf) => { for (const b of buf) usbOut.push(b); };
function usbServe() {
  if (!usbPending || !usbIn.length) return;
  const [ep, size] = usbPending;
  usbPending = null;
  const n = Math.min(size, usbIn.length);
  mcu.usbCtrl.endpointReadDone(ep, Uint8Array.from(usbIn.splice(0, n)));
}
mcu.usbCtrl.onEndpointRead = (endpoint, size) => {
  if (endpoint === cdc.outEndpoint) {
    usbPending = [endpoint, size];
    usbServe(); // answered at once only if there is data: no zero-length storm
  }
};

// ---------------------------------------------------------------- quadrature encoder
const cfg = { pwm: 16, dir: 17, en: 18, encA: 2, encB: 3, watch: [17, 18], pwmEdges: false };
const GRAY = [0, 2, 3, 1]; // (B<<1)|A for position & 3: B leads A when counting up
let encPos = 0;
let encTarget = 0;
const encEdges = []; // nanos of the pending edges of this interval
let encStep = 0;
let encWithin = 0; // ns: edges of the next interval within this much of its start (0: all of it)
function encApply(pos) {
  const v = GRAY[pos & 3];
  const a = !!(v & 1), b = !!(v & 2);
  if (mcu.gpio[cfg.encA].rawInputValue !== a) mcu.gpio[cfg.encA].setInputValue(a);
  if (mcu.gpio[cfg.encB].rawInputValue !== b) mcu.gpio[cfg.encB].setInputValue(b);
}
const ENC_GAP_NS = 250; // shortest spacing of two edges: 31 cycles, several PIO sampling passes
const encAlarm = clock.createAlarm(() => {
  encPos += encStep;
  encApply(encPos);
  encEdges.shift();
  if (encEdges.length) encAlarm.schedule(encEdges[0] - clock.nanos);
});
function encPlan(intervalNanos) {
  // edges still pending from an earlier interval are planned again from where the pins are (one
  // edge at a time: applying them at once would jump the Gray code by several states, which the
  // decoder reads as no count or as a count the wrong way), then spread over this interval's first
  // encWithin -- never closer than ENC_GAP_NS: a jump too large for the interval goes on into the
  // next ones, as a fast real encoder's edges would
  encEdges.length = 0;
  encAlarm.cancel();
  encApply(encPos);
  const n = Math.abs(encTarget - encPos);
  if (!n) return;
  encStep = encTarget > encPos ? 1 : -1;
  const t0 = clock.nanos;
  const span = encWithin > 0 && encWithin < intervalNanos ? encWithin : intervalNanos;
  const gap = Math.max(span / n, ENC_GAP_NS);
  for (let k = 0; k < n; k++) encEdges.push(t0 + (k + 0.5) * gap);
  encAlarm.schedule(encEdges[0] - t0);
}
encApply(0);

// ---------------------------------------------------------------- observation
let edges = [];
let pwmEvents = [];
const listeners = new Map();
function levelOf(pin) {
  const v = mcu.gpio[pin].value;
  return v === 1 ? 1 : v === 0 ? 0 : null; // null: not driven (input)
}
function watchPins() {
  for (const off of listeners.values()) off();
  listeners.clear();
  const pins = new Set(cfg.watch);
  if (cfg.pwmEdges) pins.add(cfg.pwm);
  for (const p of pins) {
    listeners.set(p, mcu.gpio[p].addListener((value) => {
      edges.push([p, Math.round(clock.nanos / NS_PER_CYCLE), value === 1 ? 1 : value === 0 ? 0 : null]);
    }));
  }
}
watchPins();
function pwmSlice() { return (cfg.pwm >> 1) & 7; }
function pwmState() {
  const ch = mcu.pwm.channels[pwmSlice()];
  const b = cfg.pwm & 1;
  const cc = b ? ch.cc >>> 16 : ch.cc & 0xffff;
  const ccActive = b ? ch.alarmB.target : ch.alarmA.target;
  return {
    slice: pwmSlice(), channel: b ? 'B' : 'A',
    compare: cc, top: ch.top, enabled: !!(ch.csr & 1), div: ch.div,
    compare_active: ccActive, top_active: ch.timer.top,
    phase_correct: !!(ch.csr & 2), inverted: !!(ch.csr & (b ? 8 : 4)),
    pin_function_pwm: mcu.gpio[cfg.pwm].functionSelect === 4,
  };
}
// record PWM register writes of the watched slice (the firmware's duty/enable history)
{
  const orig = mcu.pwm.writeUint32.bind(mcu.pwm);
  mcu.pwm.writeUint32 = (offset, value) => {
    orig(offset, value);
    const s = pwmSlice();
    if ((offset < 0xa0 && Math.floor(offset / 0x14) === s) || offset === 0xa0) {
      const p = pwmState();
      pwmEvents.push([Math.round(clock.nanos / NS_PER_CYCLE), p.compare, p.top, p.enabled ? 1 : 0, p.div]);
    }
  };
}


// ---------------------------------------------------------------- loop probe
// The firmware's paced loop (App.run) busy-waits for its deadline reading ticks_us() -- the
// TIMER's raw count -- every few microseconds, and reads it at the start and end of each step;
// a loop iteration (step + link poll) reads it rarely.  So the reads form clusters (at least
// min_reads reads, each within gap_us of the previous): a wait.  The last read of a cluster
// starts an iteration (the step's own first ticks_us()), the first read of the next cluster
// ends it (the loop's deadline check after the poll).  An overrun leaves no wait, but the
// loop's deadline reset and its checks still read the TIMER back to back: a short cluster.
// Measured in emulated cycles, from the outside: the firmware is not changed.
const probe = { on: false, gap: 40 * 125, minReads: 3, raw: false, last: -Infinity, run: 0, runStart: 0,
                iterStart: null, iters: [], reads: [] };
function probeRead() {
  const c = cyc; // cycle count at the start of the instruction doing the read
  const p = probe;
  if (p.raw) p.reads.push(c);
  if (c - p.last <= p.gap) {
    p.run++;
  } else {
    if (p.run >= p.minReads) p.iterStart = p.last;
    p.run = 1;
    p.runStart = c;
  }
  if (p.run === p.minReads && p.iterStart !== null) {
    p.iters.push([p.iterStart, p.runStart]);
    p.iterStart = null;
  }
  p.last = c;
}
{
  const timer = mcu.peripherals[0x40054];
  const orig = timer.readUint32.bind(timer);
  timer.readUint32 = (offset) => {
    // TIMELR 0x0c, TIMERAWH 0x24, TIMERAWL 0x28
    if (probe.on && (offset === 0x28 || offset === 0x0c)) probeRead();
    return orig(offset);
  };
}

// ---------------------------------------------------------------- ADC inputs (open wiper)
// {"cmd":"adc","ch":C,"value":V,"open":true}: the pin of channel C (GP26+C) is left floating, as an
// open potentiometer wiper: it reads V (where it floats to) with no pad pull, 0 with the pad's
// pull-down and 4095 with its pull-up enabled (the pad's pull overpowers nothing else).  Without
// "open" the channel is driven: it reads V whatever the pulls (a low-impedance source).
const adcOpen = [false, false, false, false];
{
  const set = mcu.adc.channelValues.slice();
  for (let ch = 0; ch < 4; ch++) {
    Object.defineProperty(mcu.adc.channelValues, ch, {
      get() {
        if (!adcOpen[ch]) return set[ch];
        const pad = mcu.gpio[26 + ch].padValue;
        return pad & 8 ? 4095 : pad & 4 ? 0 : set[ch];
      },
      set(v) { set[ch] = v; },
    });
  }
}

// ---------------------------------------------------------------- flash programming
// MicroPython writes its filesystem with the SDK's flash_range_erase/flash_range_program, which
// call bootrom routines found through the ROM function table (connect_internal_flash,
// flash_exit_xip, flash_range_erase, flash_range_program, flash_flush_cache, flash_enter_cmd_xip)
// that drive the flash chip through the SSI -- not modelled by rp2040js.  Each routine's first
// instruction is replaced by BKPT #ROM_BKPT; the break handler does the routine's work on the flash
// array (erase: 0xff over whole 4 KiB sectors; program: NOR semantics, old & new) and returns to LR.
// The rest of the SDK sequence (boot2 copied to RAM and re-run to re-enter XIP) runs as on a chip.
//
// Power cut ("power_cut" request): armed with a flash-operation index k and a byte count m, the
// k-th erase/program from then on does only its first m bytes (a torn operation; m >= its length:
// the operation completes), and the core stops right there as if the supply went away.  The flash
// array (read with "flash") is then what the chip would power up with.
const ROM_BKPT = 0xf1;
const romFuncs = new Map(); // address (thumb bit clear) -> name
let flashOps = 0; // erase/program operations since power-on
let flashBytes = 0; // bytes erased or programmed since power-on
let cut = null; // {op, keep} while a power cut is armed
let flashLog = null; // [kind, offset, count, hex data (program)] of each operation, while logging
let powerCut = false;
{
  const rom16 = (a) => (mcu.bootrom[a >> 2] >>> ((a & 2) * 8)) & 0xffff;
  const code = (s) => s.charCodeAt(0) | (s.charCodeAt(1) << 8);
  const want = new Map([['IF', 'connect_internal_flash'], ['EX', 'flash_exit_xip'], ['RE', 'flash_range_erase'],
    ['RP', 'flash_range_program'], ['FC', 'flash_flush_cache'], ['CX', 'flash_enter_cmd_xip']]);
  for (let t = rom16(0x14); rom16(t) !== 0; t += 4) {
    for (const [k, name] of want) if (rom16(t) === code(k)) romFuncs.set(rom16(t + 2) & ~1, name);
  }
  if (romFuncs.size !== want.size) throw new Error(`bootrom flash routines not found (${[...romFuncs.values()]})`);
  for (const a of romFuncs.keys()) {
    const w = a >> 2, sh = (a & 2) * 8;
    mcu.bootrom[w] = ((mcu.bootrom[w] & ~(0xffff << sh)) | ((0xbe00 | ROM_BKPT) << sh)) >>> 0;
  }
}
function flashOp(kind, addr, count, data) {
  // one erase or program of count bytes at flash offset addr; false: the power went away in it
  let n = count;
  let stop = false;
  if (cut !== null && cut.op-- === 0) {
    n = Math.max(0, Math.min(count, cut.keep));
    cut = null;
    stop = true;
  }
  const f = mcu.flash;
  if (flashLog !== null) {
    const d = [];
    if (kind === 'program') for (let i = 0; i < count; i++) d.push(mcu.readUint8(data + i));
    flashLog.push([kind, addr, count, hex(d)]);
  }
  xipFlush(); // the cache would serve stale lines (the SDK flushes it after each operation too)
  if (kind === 'erase') f.fill(0xff, addr, addr + n);
  else for (let i = 0; i < n; i++) f[addr + i] &= mcu.readUint8(data + i);
  flashOps++;
  flashBytes += n;
  if (stop) {
    powerCut = true;
    halted = true;
    breakCode = 'power_cut';
  }
  return !stop;
}
function romServe(code) {
  if (code !== ROM_BKPT) return false;
  const pc = (core.PC - 2) >>> 0;
  const name = romFuncs.get(pc);
  if (name === undefined) return false;
  const r = core.registers;
  if (name === 'flash_range_erase') {
    const a0 = r[0] & ~0xfff;
    const a1 = (r[0] + r[1] + 0xfff) & ~0xfff;
    if (a1 > a0 && !flashOp('erase', a0, a1 - a0, 0)) return true;
  } else if (name === 'flash_range_program') {
    if (r[2] > 0 && !flashOp('program', r[0] >>> 0, r[2] >>> 0, r[1] >>> 0)) return true;
  } else if (name === 'flash_flush_cache') {
    xipFlush(true);
  }
  core.PC = r[14] & ~1; // return to the caller
  return true;
}

// ---------------------------------------------------------------- XIP flash cache model
// rp2040js serves every read of the XIP window (0x10000000-0x13ffffff) from the flash array at
// the cost of a RAM read.  On the chip those reads go through the XIP cache: 16 KiB, two-way set
// associative, 8-byte lines (1024 sets), LRU replacement; a hit costs what a RAM read costs, a
// miss stalls the bus while the SSI reads the line from the QSPI flash.  Here every CPU read of
// the window (instruction fetches, literal pools, rodata, vector fetches) goes through that model
// and each miss adds XIP_MISS_CYCLES to the instruction doing it.  The aliases behave as in the
// datasheet (2.6.3.1): 0x10 check + allocate, 0x11 check, no allocate, 0x12 no check (always a
// flash read) but allocate, 0x13 neither.  XIP_CTRL (0x14000000) is served: CTRL.EN (0: every
// access goes to flash), FLUSH, STAT, and the CTR_HIT/CTR_ACC counters (0x0c/0x10; write clears).
// The cache is flushed on every flash erase/program, on flash_flush_cache and on a chip reset; a
// flush the firmware asks for (FLUSH, flash_flush_cache) stalls the core XIP_FLUSH_CYCLES.
//
// Miss penalty (--xip-miss CYCLES, default XIP_MISS_DEFAULT): the Pico's boot2 (W25Q080) runs the
// SSI in quad-I/O continuous read (0xEB with mode bits 0xA0, no command phase) at SCK = clk_sys/2.
// A line fill is 24 address + 8 mode bits on 4 lines (8 SCK), 4 dummy SCK, 64 data bits on 4 lines
// (16 SCK) = 28 SCK = 56 clk_sys cycles -- the same count for the chip the Pico carries, Winbond's
// W25Q16JV (datasheet "Fast Read Quad I/O (EBh)" with continuous read mode M5-4 = 10: 6 address
// + 2 mode clocks, 4 dummy clocks, 2 clocks a byte; no instruction phase), plus the SSI/XIP handshake (chip select, the SSI's RX
// path, the bus stall's own cycle): XIP_MISS_OVERHEAD cycles (a parameter, set from the perf_bench
// calibration in docs/firmware.md).  --xip-cache off (or {"cmd":"xip","on":false}) switches it off.
// CTR_ACC counts the M0+'s bus accesses: an instruction fetch is one 32-bit access per word (the
// core fetches two 16-bit instructions at once); the emulator's per-instruction halfword fetches
// of the same word are counted once.
const XIP_MISS_FLASH = 56; // 28 SCK at clkdiv 2
const XIP_MISS_OVERHEAD = 8;
const XIP_MISS_DEFAULT = XIP_MISS_FLASH + XIP_MISS_OVERHEAD;
const XIP_SETS = 1024;
const XIP_FLUSH_CYCLES = 2000; // datasheet 2.6.3.2: a flush zeroes the tags in "around 2000 clock cycles"; the core stalls
const xip = {
  on: (args['xip-cache'] ?? 'on') !== 'off',
  miss: Number(args['xip-miss'] ?? XIP_MISS_DEFAULT),
  enabled: true, // XIP_CTRL.EN
  tags: new Int32Array(2 * XIP_SETS).fill(-1), // line number held by way w of set s at [2 s + w]
  lru: new Uint8Array(XIP_SETS), // the way to replace next in each set
  last: -1, // line of the last cached access (a repeat is a hit that changes nothing)
  lastWord: -1, // word of the last instruction fetch (CTR_ACC: one access per 32-bit fetch)
  stall: 0, // cycles owed by the instruction being executed
  hit: 0, acc: 0, // XIP_CTRL CTR_HIT / CTR_ACC (32-bit)
  misses: 0, stallTotal: 0, flushes: 0, // statistics since power-on
};
if (!Number.isFinite(xip.miss) || xip.miss < 0) throw new Error(`--xip-miss must be a cycle count >= 0, got ${args['xip-miss']}`);
function xipFlush(stall = false) {
  // stall: a flush the firmware asked for (FLUSH register, the ROM's flash_flush_cache), which
  // holds the bus while the tags are cleared
  if (stall && xip.on) xip.stall += XIP_FLUSH_CYCLES;
  xip.tags.fill(-1);
  xip.lru.fill(0);
  xip.last = -1;
  xip.lastWord = -1;
  xip.flushes++;
}
function xipMiss() {
  xip.misses++;
  xip.stall += xip.miss;
}
function xipAccess(a) {
  // one CPU read of the XIP window at address a (0x10000000 <= a < 0x14000000)
  const line = (a & 0xffffff) >>> 3;
  const alias = (a >>> 24) & 3;
  xip.acc++;
  if (line === xip.last && alias < 2) { xip.hit++; return; }
  if (!xip.enabled || alias === 3) { xip.last = -1; xipMiss(); return; }
  const s = line & (XIP_SETS - 1);
  const i = s << 1;
  const t = xip.tags;
  if (alias < 2) {
    if (t[i] === line) { xip.hit++; xip.lru[s] = 1; xip.last = line; return; }
    if (t[i + 1] === line) { xip.hit++; xip.lru[s] = 0; xip.last = line; return; }
    xipMiss();
    if (alias === 1) { xip.last = -1; return; }
  } else {
    xipMiss(); // 0x12: not checked, the line is read from flash and allocated
    if (t[i] === line || t[i + 1] === line) { xip.lru[s] = t[i] === line ? 1 : 0; xip.last = line; return; }
  }
  const w = xip.lru[s];
  t[i + w] = line;
  xip.lru[s] = w ^ 1;
  xip.last = line;
}
class XipCtrl extends BasePeripheral {
  readUint32(offset) {
    switch (offset) {
      case 0x00: return xip.enabled ? 0x3 : 0x2; // CTRL: EN, ERR_BADWRITE (reset values)
      case 0x04: return 0; // FLUSH (write-only)
      case 0x08: return 0x3; // STAT: FLUSH_READY, FIFO_EMPTY
      case 0x0c: return xip.hit >>> 0;
      case 0x10: return xip.acc >>> 0;
    }
    return 0;
  }
  writeUint32(offset, value) {
    switch (offset) {
      case 0x00: xip.enabled = !!(value & 1); xip.last = -1; break;
      case 0x04: if (value & 1) xipFlush(true); break;
      case 0x0c: xip.hit = 0; break;
      case 0x10: xip.acc = 0; break;
    }
  }
}
mcu.peripherals[0x14000] = new XipCtrl(mcu, 'XIP_CTRL');
function xipInstall() {
  // route the core's reads through the model (the core's own methods: DMA reads are not CPU
  // stalls) and add each instruction's miss cycles to what it returns
  // (XIP reads are served here from the flash array, any alias: what rp2040js does, without
  // its range checks)
  const m = mcu;
  const fv = mcu.flashView;
  const size = mcu.flash.length;
  core.readUint16 = (a) => {
    if (a >>> 26 !== 4 || !xip.on) return m.readUint16(a);
    const pc = core.PC & ~1;
    if (a === pc || a === pc + 2) {
      // an instruction fetch (a 32-bit instruction's second halfword too): one access per word
      const wd = a >>> 2;
      if (wd !== xip.lastWord) {
        xip.lastWord = wd;
        xipAccess(a);
      }
    } else {
      xipAccess(a);
    }
    const o = a & 0xffffff;
    return o + 1 < size ? fv.getUint16(o, true) : m.readUint16(a);
  };
  core.readUint32 = (a) => {
    if (a >>> 26 !== 4 || !xip.on) return m.readUint32(a);
    xipAccess(a);
    return m.readUint32(a);
  };
  core.readUint8 = (a) => {
    if (a >>> 26 !== 4 || !xip.on) return m.readUint8(a);
    xipAccess(a);
    return m.readUint8(a);
  };
  const exec = core.executeInstruction.bind(core);
  core.executeInstruction = () => {
    const c = exec();
    if (xip.stall === 0) return c;
    const s = xip.stall;
    xip.stall = 0;
    xip.stallTotal += s;
    core.cycles += s;
    return c + s;
  };
}
xipInstall();
function xipState() {
  return { on: xip.on, miss_cycles: xip.miss, enabled: xip.enabled, hits: xip.hit, accesses: xip.acc,
           misses: xip.misses, stall_cycles: xip.stallTotal, flushes: xip.flushes };
}
function xipRequest(req) {
  // {"cmd":"xip","on":bool,"miss":cycles}: switch the model / change the penalty; answers its state
  if (req.on !== undefined) { xip.on = !!req.on; xip.last = -1; xip.lastWord = -1; }
  if (req.miss !== undefined) {
    const v = Number(req.miss);
    if (!Number.isFinite(v) || v < 0) return { ok: false, error: `xip miss must be a cycle count >= 0, got ${req.miss}` };
    xip.miss = v;
  }
  if (req.flush) xipFlush();
  return { ok: true, xip: xipState() };
}

// ---------------------------------------------------------------- watchdog reset
// rp2040js's watchdog counts and sets REASON, but on expiry (or a CTRL.TRIGGER write, i.e.
// machine.reset()) it only calls onWatchdogTrigger, which logs.  Here the chip is reset as the
// hardware does (PSM WDSEL as pico-sdk's watchdog_enable sets it: everything but the
// oscillators): core and NVIC, SRAM cleared, PWM, DMA, timer alarms, GPIO functions/pads and
// SIO outputs (pins fall back to pulled-down inputs), PIO machines stopped, UART FIFOs, USB
// (the CDC host model enumerates again) -- while the WATCHDOG block keeps SCRATCH0-7 and
// REASON and stops counting.  Boot2 then runs again from flash, as at power-on here.  Done
// between instructions (the trigger only marks it pending).  Each reset is reported in the
// next run answer: "resets": [[cycle, reason]] (reason: 1 timer, 2 forced).
const wdog = mcu.peripherals[0x40058];
let resetPending = 0;
let resets = [];
wdog.onWatchdogTrigger = () => {
  // stop it at once: its periodic alarm would otherwise fire again at the same instant forever
  resetPending = wdog.reason || 1;
  wdog.enable = false;
  wdog.timer.enable = false;
  wdog.alarm.enable = false;
};
function chipReset() {
  const reason = resetPending;
  resetPending = 0;
  resets.push([cyc, reason]);
  mcu.sram.fill(0);
  xipFlush();
  Object.assign(core, {
    VTOR: 0, IPSR: 0, PM: false, SPSEL: 0, nPRIV: false, currentMode: 0, waiting: false, eventRegistered: false,
    pendingInterrupts: 0, enabledInterrupts: 0, interruptNMIMask: 0, pendingNMI: false, pendingPendSV: false,
    pendingSVCall: false, pendingSystick: false, interruptsUpdated: true, SHPR2: 0, SHPR3: 0,
  });
  core.interruptPriorities = [0xffffffff, 0x0, 0x0, 0x0];
  mcu.ppb.reset();
  for (const ch of mcu.dma.channels) ch.reset();
  const timer = mcu.peripherals[0x40054];
  timer.writeUint32(0x20, 0xf); // ARMED: disarm all alarms
  timer.writeUint32(0x38, 0); // INTE
  timer.writeUint32(0x34, 0xf); // INTR
  for (const pio of mcu.pio) {
    pio.writeUint32(0, 0); // CTRL: state machines off (the wrapped writer re-plans the stepping)
    pio.pinDirections = 0;
  }
  mcu.pwm.reset();
  mcu.sio.gpioOutputEnable = 0;
  mcu.sio.gpioValue = 0;
  for (const pin of mcu.gpio) {
    pin.ctrl = 0x1f;
    pin.padValue = 0b0110110;
    pin.irqEnableMask = 0;
    pin.irqForceMask = 0;
    pin.irqStatus = 0;
  }
  gpioCache = -1;
  for (const m of uarts) {
    m.txFifo = [];
    m.txBusy = false;
    m.txAlarm.cancel();
    m.rtAlarm.cancel();
    m.baud = 0;
    m.u.rxFIFO.reset();
    m.u.interruptMask = 0;
    m.u.interruptStatus = 0;
  }
  usbConnected = false;
  usbPending = null;
  Object.assign(cdc, { initialized: false, descriptorsSize: null, descriptors: [], outEndpoint: -1, inEndpoint: -1 });
  core.registers.fill(0); // boot2 returns to LR unless it is 0 (entered from the bootrom)
  core.bankedSP = 0;
  core.reset();
  core.PC = 0x10000000;
  for (const pin of mcu.gpio) pin.checkForUpdates();
  const p = pwmState();
  pwmEvents.push([cyc, 0, p.top, 0, p.div]);
}

// ---------------------------------------------------------------- MCP2515 CAN controller on SPI
// --mcp2515 '{"spi":1,"cs":13,"int":14,"xtal":16000000}' attaches the chip model (mcp2515.mjs);
// without it nothing answers on SPI (MISO reads 0): a board with no controller fitted.
//   {"cmd":"can","frames":[[id,"<hex>"],...],"source":"host"}  frames onto the bus from an
//                                           outside node (each source a FIFO; arbitration by id)
//   {"cmd":"can_bus","error":true,"xtal":8e6} disturb the bus (every attempt an error frame) or
//                                           not; the crystal the bit time is computed from
// A "run" answer then holds can_tx ([cycle, id, hex] of the frames the chip sent) and can (the
// chip's mode, TEC/REC/EFLG, bit time, bus and SPI counters).
const can = args.mcp2515 ? new Mcp2515({ mcu, clock, nsPerCycle: NS_PER_CYCLE, ...JSON.parse(args.mcp2515) }) : null;

// ---------------------------------------------------------------- run loop
function runUntil(target) {
  while (cyc < target && !halted) {
    if (core.waiting) {
      let until = target;
      const na = clock.nextAlarm;
      if (na !== null) {
        const ac = Math.ceil(na.nanos / NS_PER_CYCLE);
        if (ac < until) until = ac < cyc ? cyc : ac;
      }
      const start = cyc;
      if (!pioLazy && pioNext <= until) {
        if (pioCanWake()) {
          // a PIO interrupt may end the wait: step cycle by cycle
          while (core.waiting && pioNext <= until) {
            cyc = Math.ceil(pioNext);
            clock.nanosCounter = cyc * NS_PER_CYCLE;
            stepPio(cyc);
          }
        } else {
          stepPio(until); // nothing the PIO does can wake the core: catch up in one go
        }
      }
      if (core.waiting) {
        cyc = until;
        setNanos(cyc * NS_PER_CYCLE);
      }
      idleCycles += cyc - start;
      if (resetPending) chipReset();
      continue;
    }
    cyc += core.executeInstruction();
    setNanos(cyc * NS_PER_CYCLE);
    if (resetPending) chipReset();
    if (!pioLazy && pioNext <= cyc) stepPio(cyc);
  }
  pioSync(); // the machines' state is current at the end of each run
}

function hex(arr) { return Buffer.from(arr).toString('hex'); }
let lastLog = 0;
function stateAnswer(extra) {
  const u0 = uarts[0];
  const tx = u0.txOut;
  const txBytes = [], txTimes = [];
  for (let i = 0; i < tx.length; i += 2) { txBytes.push(tx[i]); txTimes.push(tx[i + 1]); }
  u0.txOut = [];
  const out = {
    ok: true,
    cycles: cyc,
    us: (cyc * NS_PER_CYCLE) / 1000,
    pwm: pwmState(),
    dir: levelOf(cfg.dir),
    en: levelOf(cfg.en),
    edges,
    pwm_events: pwmEvents,
    uart_tx: hex(txBytes),
    uart_tx_t: txTimes,
    uart_baud: u0.baud,
    uart_rx_pending: u0.rxQueue.length,
    uart_overruns: u0.overruns,
    usb_tx: hex(usbOut.splice(0)),
    usb_connected: usbConnected,
    usb_rx_pending: usbIn.length,
    encoder: encPos,
    halted,
    break_code: breakCode,
    waiting: core.waiting,
    pc: core.PC >>> 0,
    idle_cycles: idleCycles,
    pio_active: pioSMs.length,
    pio_lazy: pioLazy,
    pio_skipped: pioSkipped,
    xip: xipState(),
    flash_ops: flashOps,
    flash_bytes: flashBytes,
    power_cut: powerCut,
    log: logCount > lastLog ? logTail.slice(-Math.min(logCount - lastLog, LOG_KEEP)) : [],
    resets,
    ...(can ? { can_tx: can.drainTx(), can: can.summary() } : {}),
    ...extra,
  };
  if (probe.on) {
    out.loop_iters = probe.iters;
    probe.iters = [];
    if (probe.raw) {
      out.timer_reads = probe.reads;
      probe.reads = [];
    }
  }
  lastLog = logCount;
  edges = [];
  pwmEvents = [];
  resets = [];
  return out;
}

function handle(req) {
  switch (req.cmd) {
    case 'adc':
      mcu.adc.channelValues[req.ch ?? 0] = req.value & 0xfff;
      if ((req.ch ?? 0) < 4) adcOpen[req.ch ?? 0] = !!req.open;
      return { ok: true };
    case 'encoder':
      encTarget = Math.trunc(req.count);
      encWithin = Math.max(0, Number(req.within_us ?? 0) * 1000);
      return { ok: true };
    case 'uart':
      uarts[req.id ?? 0].queueRx(Buffer.from(req.data, 'hex'));
      return { ok: true };
    case 'usb':
      for (const b of Buffer.from(req.data, 'hex')) usbIn.push(b);
      usbServe();
      return { ok: true };
    case 'run': {
      const n = Math.max(0, Math.round((req.us * 1000) / NS_PER_CYCLE));
      encPlan(n * NS_PER_CYCLE);
      const t0 = process.hrtime.bigint();
      const u0 = process.cpuUsage();
      runUntil(cyc + n);
      const wall = Number(process.hrtime.bigint() - t0) / 1e6;
      const u = process.cpuUsage(u0);
      return stateAnswer({ wall_ms: wall, cpu_ms: (u.user + u.system) / 1000 });
    }
    case 'state':
      return stateAnswer({});
    case 'config':
      if (req.pwm !== undefined) cfg.pwm = req.pwm;
      if (req.dir !== undefined) cfg.dir = req.dir;
      if (req.en !== undefined) cfg.en = req.en;
      if (req.watch !== undefined) cfg.watch = req.watch;
      if (req.pwm_edges !== undefined) cfg.pwmEdges = !!req.pwm_edges;
      if (req.pio_exact !== undefined) {
        pioSync();
        pioExact = !!req.pio_exact;
        pioMode();
      }
      if (req.loop_probe !== undefined) {
        const lp = req.loop_probe;
        probe.on = !!lp;
        if (lp) {
          probe.gap = Math.round(Number(lp.gap_us ?? 40) * 125);
          probe.minReads = Math.max(2, Math.trunc(lp.min_reads ?? 3));
          probe.raw = !!lp.raw;
        }
        probe.last = -Infinity;
        probe.run = 0;
        probe.iterStart = null;
        probe.iters = [];
        probe.reads = [];
      }
      watchPins();
      return { ok: true, config: cfg };
    case 'power_cut':
      // arm (or with op null, disarm) a power cut in a flash operation (see "flash programming")
      cut = req.op === null || req.op === undefined ? null : { op: Math.trunc(req.op), keep: Math.trunc(req.keep ?? 0) };
      return { ok: true, flash_ops: flashOps };
    case 'flash_log': {
      // {"on":true}: log every flash operation from now; answers (and clears) the log so far
      const log = flashLog ?? [];
      flashLog = req.on ? [] : null;
      return { ok: true, log };
    }
    case 'flash': {
      // read the flash array: {"offset":O,"length":L} -> base64 data
      const o = Number(req.offset ?? 0), l = Number(req.length ?? mcu.flash.length - o);
      return { ok: true, data: Buffer.from(mcu.flash.buffer, mcu.flash.byteOffset + o, l).toString('base64') };
    }
    case 'can':
      if (!can) return { ok: false, error: 'no MCP2515 attached (--mcp2515)' };
      for (const [id, data] of req.frames) can.queue(req.source ?? 'host', id & 0x7ff, Buffer.from(data, 'hex'));
      return { ok: true };
    case 'gpio_in':
      // drive a GPIO input from outside ({"pin":19,"value":1}; value null: undriven)
      if (req.value === null || req.value === undefined) {
        drivenPins.delete(req.pin); // let go: the pin follows its pad pull again
        followPulls();
      } else {
        drivenPins.add(req.pin);
        mcu.gpio[req.pin].setInputValue(!!req.value);
      }
      return { ok: true };
    case 'can_bus':
      if (!can) return { ok: false, error: 'no MCP2515 attached (--mcp2515)' };
      if (req.xtal) can.xtal = Number(req.xtal); // the module's crystal (a driver test swaps it)
      if (req.error !== undefined) can.setDisturbed(!!req.error);
      return { ok: true, can: can.summary() };
    case 'xip':
      return xipRequest(req);
    case 'quit':
      return { ok: true, quit: true };
  }
  return { ok: false, error: `unknown cmd ${JSON.stringify(req.cmd)}` };
}

const rl = createInterface({ input: process.stdin, crlfDelay: Infinity });
rl.on('line', (line) => {
  if (!line.trim()) return;
  let ans;
  try {
    ans = handle(JSON.parse(line));
  } catch (err) {
    ans = { ok: false, error: String(err && err.stack ? err.stack : err), log: logTail.slice(-10) };
  }
  process.stdout.write(JSON.stringify(ans) + '\n');
  if (ans.quit) process.exit(0);
});
rl.on('close', () => process.exit(0));
process.stdout.write(JSON.stringify({ ok: true, ready: true, flash_fs_offset: Number(args['fs-offset'] ?? 0xa0000) }) + '\n');
