"""A stand-in for the firmware app as the target of ``firmware/commands.py``'s dispatcher.

For the benches and tests that run the firmware's decoder, dispatcher and encoders without
the app (``host/bench/proto.py``, ``tests/test_proto_mpy.py``, ``tests/mpy_proto_board.py``):
it keeps what the commands set and answers queries with fixed, recognisable values.

Valid MicroPython and CPython; every method the dispatcher calls is allocation-free, so it
runs under ``micropython.heap_lock()``.  MicroPython on the unix port imports it (the project
root is on its path); where an interpreter sees only ``firmware/`` (the WebAssembly port),
callers paste its source (:func:`host.boards.mpyrun.standin_source`).
"""

from array import array

from firmware import msgtable as T
from firmware.commands import Target

QUIT_REF = 424242  # set_reference(QUIT_REF um) then disarm: StandIn.quit becomes True


class StandIn(Target):
    """Command target: state, faults, reference, parameters and the last gain upload."""

    def __init__(self):
        self.params = array("i", [p[5] for p in T.PARAMS])
        self.state = 0
        self.faults = 0
        self.ref = 0
        self.gains_n = 0
        self.gsum = -1
        self.quit = False
        self.epoch = 3  # arming epoch: every disarm changes it (as the app's)
        self.saves = 0

    def cmd_arm(self):
        self.state = 1
        return 0

    def cmd_disarm(self):
        self.state = 0
        self.epoch = (self.epoch + 1) & 0xFF
        if self.ref == QUIT_REF:
            self.quit = True
        return 0

    def cmd_clear_faults(self):
        self.faults = 0
        return 0

    def cmd_set_reference(self, x_um):
        self.ref = x_um
        return 0

    def param_get(self, i):
        return self.params[i]

    def param_set(self, i, v):
        self.params[i] = v
        return 0

    def gains_apply(self, buf, n):
        # an odd byte count is refused (something for the replies to differ on)
        self.gains_n = n
        s = 0
        for i in range(n):
            s += buf[i]
        self.gsum = s
        return T.R_BAD_SHAPE if n % 2 else 0

    def cmd_save(self, disp, seq):
        # nothing to store: "saved" at once
        self.saves += 1
        disp.reply(T.SAVE_CONFIG, seq, 0)
        return 0

    def fill_heartbeat(self, a):
        a[0] = self.state
        a[1] = self.faults
        a[2] = 9  # boot counter
        a[3] = self.epoch
        a[4] = 0xA5  # gains CRC, low byte
        a[5] = 0xFFFF  # uptime (ms), the field's largest value

    def fill_telemetry(self, a):
        # constants: arithmetic on a stored field value could make a big int (an
        # allocation) on a 32-bit port, whose small ints end at 2**30
        for i in range(8):
            a[i] = i - 4

    def fill_timing(self, a):
        a[0] = 1
        a[1] = 2
        a[2] = 3
        a[3] = 65535
