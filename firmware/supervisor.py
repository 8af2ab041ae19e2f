# The supervisor: owns the state machine and the latched fault flags.
#
#   DISARMED --arm--> ARMED --|tilt| < arm_tilt and timing measured--> BALANCING
#   any state --fault--> FAULT (motor off in the same tick, flags latched)
#   FAULT --clear_faults--> DISARMED (a cause still present latches again next tick)
#   ARMED/BALANCING --disarm--> DISARMED
# The motor may run only in BALANCING (and the driver enable is high only then).
# Readiness: arm is refused (R_NOT_READY) unless the active gain table passed its check and
# its CRC (`ready`, set by the app); a table that is not ready latches F_GAINS on every tick,
# whatever the state, so clear_faults cannot make it usable.  A self-paced loop (App.run)
# must also have measured its period (`timing_ok`) before ARMED may start balancing.
# Fault flags (bit: meaning; documented for the protocol in msgtable.FAULTS):
F_TILT = 1       # |tilt| beyond tilt_limit while balancing (the pendulum fell)
F_WATCHDOG = 2   # no valid frame from the host for watchdog_ms while armed/balancing
F_ADC_RAIL = 4   # angle ADC at 0 or full scale: potentiometer open, shorted or unpowered
F_ENC_JUMP = 8   # encoder step larger than the cart can move in one tick: noise/lost counts
F_TRACK = 16     # cart beyond the track (1.25 x the reference limit) while balancing
F_GAINS = 32     # the active gain table failed its check or CRC (boot/upload): not ready
F_STALL = 64     # |duty| >= stall_duty for stall_ms with no encoder count while balancing:
                 # driver dead, motor or encoder disconnected, encoder stuck (App: on by default)
F_LOOP = 128     # the paced loop failed (an allocation with the heap locked: MemoryError);
                 # motor off, the loop goes on serving the link (App.run)
F_DEADLINE = 256  # control deadline missed while armed/balancing (App.run): one gap between
                  # step starts > 10 periods, or late ticks (> 1.5 periods) beyond the budget
F_ESTOP = 512    # e-stop input asserted (active low; latched, motor and enable off at once)
F_RESET = 1024   # restarted by the hardware watchdog or a loop exception (App.reset_cause)
# Flags the app computes and hands to update() as `ext` (firmware/app.py):
F_CONFIG = 2048      # no valid saved configuration although copies exist (both corrupt): defaults
                     # in force, arming refused until a gain table is uploaded (firmware/store.py)
F_UNDERVOLT = 4096   # measured motor supply below vsup_min_mv while armed/balancing
F_ADC_OPEN = 8192    # the angle wiper is open: the pad-pull test moved the reading to the rail
# Flag a host link latches itself (firmware/link_can.py):
F_CAN = 16384        # CAN controller absent at start-up, or bus-off (latched again while the bus is off)

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from .msgtable import OK, R_BAD_STATE, R_FAULTED, R_NOT_READY

DISARMED = const(0)
ARMED = const(1)
BALANCING = const(2)
FAULT = const(3)


class Supervisor:
    def __init__(self):
        self.state = DISARMED
        self.faults = 0
        self.last = 0  # flags raised by the latest update (not latched)
        self.tilt_counts = 0  # |ADC counts from upright| that trips F_TILT
        self.arm_counts = 0  # |ADC counts| below which ARMED starts balancing
        self.track_counts = 0  # |encoder counts| that trips F_TRACK
        self.wd_ticks = 0  # watchdog in ticks (0: off)
        self.wd_count = 0
        self.stall_ticks = 0  # no-motion check in ticks (0: off)
        self.stall_duty = 800  # |duty| that must move the cart
        self.stall_count = 0
        self.ready = True  # the active gain table passed its check and CRC (App)
        self.timing_ok = True  # the loop period is measured (App.run clears it until it is)

    def arm(self):
        if self.faults or self.state == FAULT:
            return R_FAULTED
        if not self.ready:
            return R_NOT_READY
        if self.state == DISARMED:
            self.state = ARMED
            self.wd_count = 0
        return OK

    def disarm(self):
        # always accepted; a latched fault stays latched
        if self.state != FAULT:
            self.state = DISARMED
        return OK

    def clear(self):
        if self.state == ARMED or self.state == BALANCING:
            return R_BAD_STATE
        self.faults = 0
        self.state = DISARMED
        return OK

    def feed(self):
        self.wd_count = 0

    def update(self, counts, pos, rail, jump, delta=0, duty=0, ext=0):
        # one tick: check the sensors; returns True on the tick balancing starts.
        # delta: encoder counts since the last tick; duty: the duty of the last tick;
        # ext: fault flags found by the app this tick (F_ADC_OPEN, F_UNDERVOLT)
        f = ext
        if not self.ready:
            f |= F_GAINS
        if rail:
            f |= F_ADC_RAIL
        if jump:
            f |= F_ENC_JUMP
        st = self.state
        # (limits read once into locals: the viper build, fasttick.py, is generated from this)
        if st == BALANCING:
            # a railed ADC is no angle measurement: F_ADC_RAIL alone names the cause
            t = self.tilt_counts
            if not rail and (counts > t or counts < -t):
                f |= F_TILT
            t = self.track_counts
            if pos > t or pos < -t:
                f |= F_TRACK
            n = self.stall_ticks
            if n > 0:
                t = self.stall_duty
                if delta != 0:
                    self.stall_count = 0
                elif duty >= t or duty <= -t:
                    c = self.stall_count + 1
                    self.stall_count = c
                    if c > n:
                        f |= F_STALL
        n = self.wd_ticks
        if (st == ARMED or st == BALANCING) and n > 0:
            c = self.wd_count + 1
            self.wd_count = c
            if c > n:
                f |= F_WATCHDOG
        self.last = f
        if f:
            self.faults |= f
            self.state = FAULT
            return False
        if self.faults:
            # latched but no longer present: stay in FAULT until cleared
            self.state = FAULT
            return False
        if st == ARMED and self.timing_ok and -self.arm_counts < counts and counts < self.arm_counts:
            self.state = BALANCING
            self.stall_count = 0
            return True
        return False
