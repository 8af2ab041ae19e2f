# HIL entry point: the unchanged firmware app, its sensors and motor replaced by the link.
#
# Runs under the MicroPython unix port on a pty (host/boards/vport.py starts it) or on a real
# board in HIL mode: the board's main.py runs it in lockstep over its own link after a MODE
# hil command (no reflash; MODE robot or a reset goes back), or by hand with a machine.UART:
#   from firmware import main_hil; main_hil.main("/dev/pts/3", link="serial", mode="lockstep")
#   main_hil.main(uart=machine.UART(0, 1000000), mode="realtime")
# (a machine.UART is wrapped in BoardUART; a board's main.py can also pass heap_lock=True)
#
# link  "serial": COBS frames (framing.py); "can": python-can `serial`-interface frames
#       (canframe.py) on the same byte stream, node id `node`.
# mode  "lockstep": one app.step() per received HIL_SENSOR frame, answered by one
#       HIL_ACTUATOR frame with the same tick -- deterministic, as fast as the link goes.
#       "realtime": the app paces itself (app.run(): one step per period on ticks_us);
#       this object is the app's link: its poll(), called after every step, answers the
#       sensor frame the step used, sends telemetry/heartbeat, then serves the link
#       (latching sensor frames, dispatching commands) until just before the next step,
#       so a frame that arrives before a step is the one that step uses.
# Both modes decode every other frame through commands.Dispatcher (arm, parameters,
# requests...) and send telemetry every telem_div steps and a heartbeat every
# heartbeat_ms of board time (pacer.Pacer, as the board's own link does; in lockstep a
# host that sends nothing still gets heartbeats, _IDLE_MS of board time per idle wait).
# The loop allocates nothing: app.run() holds the heap lock in real time, main() takes
# it in lockstep when asked (tests/test_hil_*.py).  main() returns 0 when the host hangs up.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from array import array

from . import codec
from . import commands
from . import crc16
from . import msgtable as T
from .fixmath import ticks_add, ticks_diff
from .hal_hil import HilHal
from .hilport import HilPort
from . import emitter

_RX = const(256)
_IDLE_MS = const(50)
_IDLE_US = const(50000)
# real time: stop serving the link this long before the next step (app.run spins it)
_GUARD_US = const(250)


class HangUp(Exception):
    # the host closed the link (ends app.run(); raised once, at the very end)
    pass


class BoardUART(HilPort):
    # machine.UART -> the surface HilMain uses: wait(timeout_ms), any(), readinto(buf, n),
    # write(buf, n).  machine.UART.write takes a whole buffer, so the slices of the
    # (single) transmit buffer are made once, the first time it is seen.
    def __init__(self, uart):
        import select
        self.uart = uart
        self.hup = False
        self._poll = select.poll()
        self._poll.register(uart, select.POLLIN)
        for _ in self._poll.ipoll(0):
            pass
        self._buf = None
        self._views = None

    def wait(self, timeout_ms):
        for _ in self._poll.ipoll(timeout_ms):
            return True
        return False

    def any(self):
        return self.uart.any()

    def readinto(self, buf, nbytes=-1):
        if nbytes < 0:
            nbytes = len(buf)
        n = self.uart.readinto(buf, nbytes)
        return 0 if n is None else n

    def write(self, buf, nbytes=-1):
        if nbytes < 0:
            return self.uart.write(buf)
        if buf is not self._buf:
            self._slices(buf)
        return self.uart.write(self._views[nbytes])

    def _slices(self, buf):
        # (its own method: a comprehension's closure would make write() allocate a
        # cell on every call)
        mv = memoryview(buf)
        self._views = [mv[:i] for i in range(len(buf) + 1)]
        self._buf = buf


class HilMain:
    # uart: a hilport.HilPort (UnixUART, BoardUART around a machine.UART, UsbStream);
    # app_factory(hal, link) -> the firmware app (firmware.app.App or a subclass: its emitter
    # is read here and by the pacer; default App; link is this
    # object in real time, whose poll() app.run() calls after each step)
    # config: passed to the default App (e.g. {"boot": n}, see firmware/app.py); its
    # "emitter" is the board's (firmware/board.py EMITTER) unless given: HIL runs the code
    # the robot runs, on the board and on the unix port (the WebAssembly port: "bytecode")
    def __init__(self, uart, link="serial", mode="lockstep", node=1, app_factory=None, config=None):
        if link != "serial" and link != "can":
            raise ValueError("link must be 'serial' or 'can'")
        if mode != "lockstep" and mode != "realtime":
            raise ValueError("mode must be 'lockstep' or 'realtime'")
        self.uart = uart
        self.mode = mode
        self.can = link == "can"
        cfg = dict(config) if config is not None else {}
        if "emitter" not in cfg:
            from .board import EMITTER
            cfg["emitter"] = EMITTER
        em = cfg["emitter"]
        layout = codec.Layout()
        table = crc16.make_table()
        self.layout = layout
        if self.can:
            from . import canframe
            self.dec = canframe.SerialCanDecoder(layout, node, table)
            w = canframe.SerialCanWriter(layout, node, table)
            self.tx = canframe.SerialCanTx(w, uart.write)
            self.pbuf = self.dec.data
            self.poff = 0
        else:
            from . import framing
            self.dec = framing.Decoder(layout, table)
            self.tx = framing.SerialTx(framing.Encoder(layout, table, em), uart.write)
            self.pbuf = self.dec.buf
            self.poff = 2
        self.hal = HilHal(self.tx)
        rt_link = self if mode == "realtime" else None
        if app_factory is None:
            from .app import App
            self.app = App(self.hal, rt_link, None, cfg)
        else:
            self.app = app_factory(self.hal, rt_link)
        self.hal.set_status(self.app.fill_heartbeat)
        self.disp = commands.Dispatcher(self.app, layout, self.tx, table)
        self.disp.dec = self.dec
        # MODE: hil is this mode; robot/repl end a lockstep run that a board's main.py
        # started (switch=True: it then runs next_mode), else NOT_SUPPORTED
        self.switch = False
        self.next_mode = T.MODE_ROBOT
        self.disp.on_mode = self._on_mode
        self.disp.crc30 = emitter.command_crc(self.app.emitter)
        self.pacer = emitter.pacer(self.app, self.disp)
        self.rx = bytearray(_RX)
        self.sv = array("i", [0] * 4)
        self.n_steps = 0
        self.n_frames = 0
        self.running = True
        # made now: raising it at the end must not allocate (the heap may be locked)
        self._hangup = HangUp()
        # cached bound methods (no allocation when called in the loop)
        self._step = self.app.step
        self._feed = self.dec.feed
        self._readinto = uart.readinto
        self._ticks_us = self.hal.ticks_us
        # the deadline arithmetic is mod 2**30 (fixmath), whatever the port's ticks period
        self._diff = ticks_diff
        self._timing = self.app.timing
        # the link watchdog is fed by sensor frames (the HAL's n_sensor), HOST_HEARTBEAT
        # and SET_REFERENCE (commands.py), not by every frame
        # a queued SAVE_CONFIG runs between frames in lockstep (app.run does it in real
        # time); locked: main() holds the heap lock around run().  Every app has it
        # (App's part appstore.ConfigSave; without a store nothing is ever queued)
        self._save = self.app.service_save
        self.locked = False

    def _ticks_ms(self):
        return self.hal.ticks_ms()

    def _on_mode(self, m):
        if m == T.MODE_HIL:
            return T.OK
        if not self.switch or self.mode != "lockstep":
            return T.R_NOT_SUPPORTED
        self.next_mode = m
        self.running = False
        return T.OK

    # ---- input ----
    def _on_frame(self, mid, step_now):
        # a decoded frame; returns True if it was a sensor frame
        self.n_frames += 1
        seq = 0 if self.can else self.dec.seq
        if mid == T.HIL_SENSOR:
            sv = self.sv
            self.layout.unpack(mid, self.pbuf, self.poff, sv, 0)
            self.hal.on_sensor(sv[0], sv[1], sv[2], seq)
            if step_now:
                self._tick()
            return True
        self.disp.handle(mid, seq, self.pbuf, self.poff)
        return False

    def _drain(self, step_now):
        # read and decode what is waiting; returns the byte count (0: nothing or hang-up)
        n = self._readinto(self.rx, _RX)
        rx = self.rx
        feed = self._feed
        for i in range(n):
            mid = feed(rx[i])
            if mid >= 0:
                self._on_frame(mid, step_now)
        return n

    # ---- one control tick ----
    def _tick(self):
        # lockstep: one step for the sensor frame just latched, answered at once
        self._step()
        self.hal.end_tick()
        self.n_steps += 1
        self.pacer.tick()

    # ---- the loops ----
    def run_lockstep(self):
        uart = self.uart
        while self.running:
            if not uart.wait(_IDLE_MS):
                self.pacer.elapse(_IDLE_US)
                continue
            if self._drain(True) == 0 and self._hung_up():
                return 0
            if self.app.save_seq >= 0:
                self._save(self.locked)
        return 0

    def poll(self):
        # real time, called by app.run() after each step: answer, periodic messages,
        # then serve the link until _GUARD_US before the next step
        self.hal.end_tick()
        self.n_steps += 1
        self.pacer.tick()
        uart = self.uart
        deadline = ticks_add(self._timing.last_us, self.app.period_us)
        diff = self._diff
        ticks = self._ticks_us
        while True:
            left = diff(deadline, ticks()) - _GUARD_US
            if left <= 0:
                break
            if uart.wait(left // 1000):
                if self._drain(False) == 0 and self._hung_up():
                    raise self._hangup
        if uart.any():
            self._drain(False)

    def run_realtime(self):
        try:
            self.app.run()
        except HangUp:
            pass
        return 0

    def _hung_up(self):
        return self.uart.hup

    def run(self):
        if self.mode == "lockstep":
            return self.run_lockstep()
        return self.run_realtime()


def main(port=None, link="serial", mode="lockstep", node=1, uart=None, heap_lock=False, boot_file=None,
         config_dir=None):
    # port: tty path for the unix port; uart: a ready UART object (a board).
    # heap_lock: lockstep runs under micropython.heap_lock() -- any allocation in it then
    # raises MemoryError and ends the run (tests use it as the allocation proof).  Real
    # time is always locked by app.run(), where an allocation latches F_LOOP (motor off).
    desktop = uart is None
    if uart is None:
        from .uart_unix import UnixUART
        uart = UnixUART(port)
    elif not isinstance(uart, HilPort):
        uart = BoardUART(uart)
    # boot_file: where the boot counter persists (a board: a file on its flash); each
    # start increments it and HEARTBEAT.boot reports it, so the host sees a reset
    config = None
    if boot_file is not None:
        from .boot import boot_count
        from .session import seed
        config = {"boot": boot_count(boot_file), "seed": seed(boot_file + ".seed")}
    if desktop:
        # the unix port on a desktop OS has no real-time guarantee (the hypervisor steals
        # tens of ms): late ticks are counted, F_DEADLINE is a board's (App "deadline")
        config = config or {}
        config["deadline"] = False
    m = HilMain(uart, link, mode, node, None, config)
    # config_dir: where the saved configuration lives (two copies, firmware/store.py);
    # loaded now, written by SAVE_CONFIG
    if config_dir is not None:
        from .store import ConfigStore
        m.app.attach_store(ConfigStore(config_dir))
    lock = heap_lock and mode == "lockstep"
    m.locked = lock
    if lock:
        import gc
        import micropython
        gc.collect()
        micropython.heap_lock()
    try:
        return m.run()
    finally:
        if lock:
            import micropython
            micropython.heap_unlock()
        uart.close()
