# upright protocol: THE message table (single source of truth).
#
# Firmware and host both read this module; host/link/messages.py builds typed message
# classes from it, host/link/dbc.py renders the CAN database and docs/protocol.md is the
# generated reference.  Nothing in here runs except literal data and const().
#
# Wire rules (both framings carry the same payload bytes):
# - every payload is little-endian and at most 8 bytes (one classic CAN frame);
#   data longer than 8 bytes is never one message: telemetry is split into
#   TELEM_STATE + TELEM_CTRL (same tick), and the gain table travels as
#   GAINS_BEGIN, GAINS_CHUNK x N (6 data bytes each, in offset order), GAINS_COMMIT;
# - serial: COBS([id u8][seq u8][payload][crc16 big-endian]) between 0x00
#   delimiters (one before and one after every frame); crc16 is CRC-16/CCITT-FALSE
#   (poly 0x1021, init 0xFFFF, no reflection, xorout 0) over id, seq and payload,
#   so the CRC over the whole unstuffed frame including its CRC is 0;
# - CAN: 11-bit id = node_id << 5 | msg_id (ODrive CAN Simple layout), DLC = the
#   payload length, no seq and no extra CRC (CAN has its own);
# - field formats are struct codes: B u8, b i8, H u16, h i16, I u32, i i32, Ns N raw
#   bytes.  The firmware keeps ints small (|v| < 2**30): a received u32 keeps its low
#   30 bits (ticks wrap at 2**30 like time.ticks_us), a received i32 saturates at
#   +-(2**30-1); values it sends stay in that range.
# - a field's physical value = raw * scale, in the unit given.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

# ---- message ids (5 bits: 0..31) ----
HEARTBEAT = const(1)
HIL_SENSOR = const(2)
HIL_ACTUATOR = const(3)
TELEM_STATE = const(4)
TELEM_CTRL = const(5)
TIMING = const(6)
SET_REFERENCE = const(7)
ARM = const(8)
DISARM = const(9)
CLEAR_FAULTS = const(10)
PARAM_GET = const(11)
PARAM_SET = const(12)
PARAM_VALUE = const(13)
GAINS_BEGIN = const(14)
GAINS_CHUNK = const(15)
GAINS_COMMIT = const(16)
REQUEST = const(17)
ACK = const(18)
NACK = const(19)

MAX_ID = const(31)
MAX_PAYLOAD = const(8)
# serial frame: id, seq, payload, crc16
MAX_FRAME = const(12)
# COBS adds one byte per 254 and the two 0x00 delimiters
MAX_WIRE = const(15)
NODE_BITS = const(6)
MSG_BITS = const(5)
# gain table upload: data bytes per chunk, largest table accepted
CHUNK_BYTES = const(6)
GAINS_MAX = const(1536)

# direction of a message
TO_BOARD = const(1)
TO_HOST = const(2)

# ---- the table ----
# (id, name, direction, doc, fields)
# field: (name, format, scale, unit, doc)
MESSAGES = (
    (HEARTBEAT, "heartbeat", TO_HOST,
     "Periodic board status (every heartbeat_ms, and on REQUEST); a changed boot counter means the board reset.",
     (("state", "B", 1, "", "supervisor state (see STATES)"),
      ("faults", "H", 1, "", "latched fault flags (bits named by the firmware supervisor)"),
      ("boot", "B", 1, "", "boot counter mod 256, incremented on every start"),
      ("uptime_ms", "I", 1, "ms", "time since boot, wraps at 2**30 ms"))),
    (HIL_SENSOR, "hil_sensor", TO_BOARD,
     "HIL: the simulated sensors for one control tick; in lockstep the board runs one step per frame.",
     (("tick", "I", 1, "", "tick number of this sample, wraps at 2**30"),
      ("adc", "H", 1, "count", "angle potentiometer ADC counts"),
      ("enc", "H", 1, "count", "quadrature encoder counter (16-bit, wraps)"))),
    (HIL_ACTUATOR, "hil_actuator", TO_HOST,
     "HIL: the motor command the board computed for the sensor frame with the same tick.",
     (("tick", "I", 1, "", "tick of the sensor frame this answers"),
      ("duty", "h", 1, "", "motor duty, -32767..32767 = fraction of V_supply"),
      ("state", "B", 1, "", "supervisor state (see STATES)"),
      ("faults", "B", 1, "", "low 8 bits of the latched fault flags"))),
    (TELEM_STATE, "telem_state", TO_HOST,
     "Telemetry part 1: estimated state (every telemetry_div ticks, and on REQUEST).",
     (("x", "h", 0.0001, "m", "estimated cart position"),
      ("xdot", "h", 0.001, "m/s", "estimated cart speed"),
      ("phi", "h", 0.0001, "rad", "estimated tilt from upright"),
      ("phidot", "h", 0.001, "rad/s", "estimated tilt rate"))),
    (TELEM_CTRL, "telem_ctrl", TO_HOST,
     "Telemetry part 2: reference, command and step time of the same tick as the preceding TELEM_STATE.",
     (("ref", "h", 0.0001, "m", "cart position reference"),
      ("force", "h", 0.01, "N", "commanded cart force after saturation"),
      ("duty", "h", 1, "", "motor duty sent to the driver"),
      ("step_us", "H", 1, "us", "duration of this control step"))),
    (TIMING, "timing", TO_HOST,
     "Loop timing statistics since the last TIMING (sent on REQUEST).",
     (("step_min_us", "H", 1, "us", "shortest control step"),
      ("step_max_us", "H", 1, "us", "longest control step"),
      ("period_max_us", "H", 1, "us", "longest time between two step starts"),
      ("overruns", "H", 1, "", "steps that missed their deadline (saturates at 65535)"))),
    (SET_REFERENCE, "set_reference", TO_BOARD,
     "Set the cart position reference; refused (OUT_OF_RANGE) beyond +-ref_limit_um. ACK or NACK.",
     (("x_um", "i", 1e-6, "m", "cart position reference"),)),
    (ARM, "arm", TO_BOARD,
     "Arm the motor (disarmed -> armed); refused (FAULTED) while a fault is latched. ACK or NACK.",
     ()),
    (DISARM, "disarm", TO_BOARD,
     "Disarm: motor off, always accepted. ACK.",
     ()),
    (CLEAR_FAULTS, "clear_faults", TO_BOARD,
     "Clear latched faults (only while disarmed; a still-present cause latches again). ACK or NACK.",
     ()),
    (PARAM_GET, "param_get", TO_BOARD,
     "Read a parameter (see PARAMS); answered by PARAM_VALUE or NACK(BAD_INDEX).",
     (("index", "B", 1, "", "parameter index"),)),
    (PARAM_SET, "param_set", TO_BOARD,
     "Write a parameter; checked against PARAMS min/max first; answered by PARAM_VALUE (the value now in force) or NACK.",
     (("index", "B", 1, "", "parameter index"),
      ("value", "i", 1, "", "new value in the parameter's unit"))),
    (PARAM_VALUE, "param_value", TO_HOST,
     "A parameter's current value (reply to PARAM_GET / PARAM_SET).",
     (("index", "B", 1, "", "parameter index"),
      ("value", "i", 1, "", "value in the parameter's unit"))),
    (GAINS_BEGIN, "gains_begin", TO_BOARD,
     "Start a gain-table upload: total length and CRC-16/CCITT-FALSE of the whole table. ACK or NACK(BAD_LENGTH).",
     (("nbytes", "H", 1, "B", "table length in bytes (1..GAINS_MAX)"),
      ("crc", "H", 1, "", "CRC-16/CCITT-FALSE of the table bytes"))),
    (GAINS_CHUNK, "gains_chunk", TO_BOARD,
     "Table bytes [offset, offset+6) in offset order, the last chunk zero-padded. ACK (a repeat of the previous chunk is ACKed again) or NACK(BAD_SEQUENCE, upload aborted).",
     (("offset", "H", 1, "B", "byte offset of this chunk, multiple of 6"),
      ("data", "6s", 1, "", "six table bytes"))),
    (GAINS_COMMIT, "gains_commit", TO_BOARD,
     "Check length and CRC and apply the table atomically; only while the motor is off (disarmed or fault). ACK or NACK (old table kept).",
     ()),
    (REQUEST, "request", TO_BOARD,
     "Ask the board to send one message now (heartbeat, telem_state, timing). Answered by that message or NACK.",
     (("msg_id", "B", 1, "", "id of the message wanted"),)),
    (ACK, "ack", TO_HOST,
     "A command was accepted.",
     (("msg_id", "B", 1, "", "id of the accepted command"),
      ("seq", "B", 1, "", "seq of the accepted serial frame (0 on CAN)"))),
    (NACK, "nack", TO_HOST,
     "A command was refused and changed nothing.",
     (("msg_id", "B", 1, "", "id of the refused command"),
      ("reason", "B", 1, "", "reason code (see REASONS)"),
      ("seq", "B", 1, "", "seq of the refused serial frame (0 on CAN)"))),
)

# ---- refusal reasons (NACK.reason; also the return codes of the target methods) ----
OK = const(0)
R_UNKNOWN = const(1)
R_OUT_OF_RANGE = const(2)
R_BAD_INDEX = const(3)
R_READ_ONLY = const(4)
R_FAULTED = const(5)
R_ARMED = const(6)
R_BAD_STATE = const(7)
R_BAD_LENGTH = const(8)
R_BAD_CRC = const(9)
R_BAD_SEQUENCE = const(10)
R_INCOMPLETE = const(11)
R_BAD_SHAPE = const(12)
R_UNSTABLE = const(13)
R_NOT_SUPPORTED = const(14)

REASONS = (
    (OK, "ok", "accepted"),
    (R_UNKNOWN, "unknown", "not a command the board accepts (wrong direction or unknown id)"),
    (R_OUT_OF_RANGE, "out_of_range", "a value is outside its documented range (e.g. reference beyond ref_limit_um)"),
    (R_BAD_INDEX, "bad_index", "no parameter with this index"),
    (R_READ_ONLY, "read_only", "parameter cannot be written"),
    (R_FAULTED, "faulted", "a fault is latched: clear it first (arming refused)"),
    (R_ARMED, "armed", "only allowed while the motor is off (gain table, some parameters)"),
    (R_BAD_STATE, "bad_state", "not allowed in the current supervisor state"),
    (R_BAD_LENGTH, "bad_length", "gain table length is 0, too long, or not the expected size"),
    (R_BAD_CRC, "bad_crc", "gain table CRC does not match the bytes received"),
    (R_BAD_SEQUENCE, "bad_sequence", "gain chunk out of order, or no upload in progress"),
    (R_INCOMPLETE, "incomplete", "commit before all gain table bytes arrived"),
    (R_BAD_SHAPE, "bad_shape", "gain table header/shape does not match the firmware"),
    (R_UNSTABLE, "unstable", "gain table rejected by the firmware's stability/finiteness check"),
    (R_NOT_SUPPORTED, "not_supported", "the board does not implement this request"),
)

# ---- supervisor states (HEARTBEAT.state); the supervisor (firmware app) owns the logic ----
STATES = (
    (0, "disarmed", "motor off, commands accepted"),
    (1, "armed", "motor enabled, waiting to catch the pendulum near upright"),
    (2, "balancing", "closed loop running"),
    (3, "fault", "motor off, a fault is latched until clear_faults"),
)

# ---- parameters (PARAM_GET / PARAM_SET) ----
P_TILT_LIMIT = const(0)
P_WATCHDOG_MS = const(1)
P_LOOP_RATE = const(2)
P_REF_LIMIT = const(3)
P_MAX_DUTY = const(4)
P_TELEM_DIV = const(5)
P_HEARTBEAT_MS = const(6)
P_NODE_ID = const(7)
P_ARM_TILT = const(8)
N_PARAMS = const(9)

# (index, name, unit, min, max, default, doc); every value an int with |v| < 2**30
PARAMS = (
    (P_TILT_LIMIT, "tilt_limit_mrad", "mrad", 50, 1500, 500,
     "tilt beyond which the supervisor cuts the motor and latches a fault"),
    (P_WATCHDOG_MS, "watchdog_ms", "ms", 10, 10000, 250,
     "command watchdog: no valid frame from the host for this long -> motor off, fault"),
    (P_LOOP_RATE, "loop_rate_hz", "Hz", 50, 2000, 500,
     "control loop rate (the gain table must match; change only while disarmed)"),
    (P_REF_LIMIT, "ref_limit_um", "um", 0, 1000000, 800000,
     "largest |cart reference| accepted by set_reference (track half-length minus margin)"),
    (P_MAX_DUTY, "max_duty", "", 0, 32767, 32767,
     "motor duty clamp, 32767 = full supply voltage"),
    (P_TELEM_DIV, "telem_div", "ticks", 0, 10000, 10,
     "send TELEM_STATE/TELEM_CTRL every this many control ticks (0 = off)"),
    (P_HEARTBEAT_MS, "heartbeat_ms", "ms", 0, 10000, 100,
     "heartbeat period (0 = only on REQUEST)"),
    (P_NODE_ID, "node_id", "", 0, 63, 1,
     "CAN node id (CAN id = node_id << 5 | msg_id)"),
    (P_ARM_TILT, "arm_tilt_mrad", "mrad", 10, 500, 50,
     "armed -> balancing only once |tilt| is below this"),
)
