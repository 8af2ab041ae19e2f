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
#   payload length, no seq and no extra CRC on a CAN bus (CAN has its own);
# - CAN frames carried as bytes on a stream (python-can's `serial` interface format
#   0xAA, timestamp u32 LE, dlc, arbitration id u32 LE, data, 0xBB) carry a CRC of their
#   own in the timestamp field: CRC-16/CCITT-FALSE over dlc, the 4 id bytes and the data,
#   in its low 16 bits, the high 16 bits 0 (firmware/canframe.py; host/link/messages.py
#   serial_can_crc); a frame whose CRC does not check out is dropped and counted;
# - ids are chosen so that no single-bit error turns any board-bound command into ARM
#   and ARM and DISARM are at least 3 bits apart (tests/test_proto_integrity.py); ARM
#   carries the board's arming token (SESSION.token: 30 random bits, drawn anew at every
#   start, disarm, clear_faults and fault), so a stale, repeated or pre-reset arm is
#   refused (R_STALE_EPOCH); REQUEST and VERSION keep their ids in every version (a host
#   reads VERSION first and refuses a board whose table hash differs from its own);
# - the commands that move the cart (CHECKED: arm, set_reference, param_set, excite) end in
#   a field `check`: CRC-32/ISO-HDLC (zlib.crc32) over the message id byte and the payload
#   bytes before it, its low 32 bits (u32: the firmware compares the low 30) or, in
#   param_set (no room for 4 bytes), its low 24 bits as 3 raw bytes; GAINS_COMMIT.check is the CRC-32 of the whole table, GAINS_BEGIN carries the
#   token (an upload belongs to the session that began it).  A mismatch is R_BAD_CHECK;
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
SESSION = const(0)
HEARTBEAT = const(1)
HIL_SENSOR = const(2)
HIL_ACTUATOR = const(3)
TELEM_STATE = const(4)
TELEM_CTRL = const(5)
TIMING = const(6)
SET_REFERENCE = const(7)
DISARM = const(8)
ARM = const(29)
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
HOST_HEARTBEAT = const(20)
VERSION = const(21)
STATS_DECODE = const(22)
STATS_FRAMES = const(23)
STATS_LOOP = const(24)
SAVE_CONFIG = const(26)
SENSORS_RAW = const(27)
STATS_CAN = const(25)
# MODE (30: ids 28 and 31 are one bit from ARM) and its values
MODE = const(30)
MODE_ROBOT = const(0)
MODE_HIL = const(1)
MODE_REPL = const(2)
# EXCITE (9: two bits from ARM) and its modes (firmware/excite.py)
EXCITE = const(9)
EXC_OFF = const(0)
EXC_ADD = const(1)
EXC_OPEN = const(2)

# commands with a trailing integrity check (see the wire rules above)
CHECKED = (ARM, SET_REFERENCE, PARAM_SET, EXCITE)

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
    (SESSION, "session", TO_HOST,
     "The board's session (on REQUEST): the arming token ARM and GAINS_BEGIN must carry, and the whole board "
     "time. The token is 30 random bits (os.urandom / the RP2040's ring-oscillator bits, mixed with a seed "
     "persisted across starts), drawn anew at every start, disarm, clear_faults and fault: nothing sent "
     "before a reset or a disarm can arm after it (a replay matches with probability 2**-30).",
     (("token", "I", 1, "", "arming token (0 .. 2**30-1); HEARTBEAT.epoch is its low 8 bits"),
      ("uptime_ms", "I", 1, "ms", "time since the board started, wraps at 2**30 ms (12.4 days); not reset by a "
       "MODE switch"))),
    (HEARTBEAT, "heartbeat", TO_HOST,
     "Periodic board status (every heartbeat_ms, and on REQUEST); a changed boot counter means the board reset, "
     "a changed gains_crc that it runs another gain table (VERSION has the full CRC).",
     (("state", "B", 1, "", "supervisor state (see STATES)"),
      ("faults", "H", 1, "", "latched fault flags (see FAULTS)"),
      ("boot", "B", 1, "", "boot counter mod 256, incremented on every start"),
      ("epoch", "B", 1, "", "low 8 bits of the arming token (SESSION.token, which ARM must carry): changes with "
       "it, on every start, disarm, clear_faults and fault"),
      ("gains_crc", "B", 1, "", "low 8 bits of the active gain table's CRC-16 (VERSION.gains_crc)"),
      ("uptime_ms", "H", 1, "ms", "time since boot, low 16 bits (wraps every 65.536 s; the whole value: "
       "SESSION.uptime_ms, status value uptime_ms)"))),
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
     "Telemetry part 1: estimated state (every telemetry_div ticks, and on REQUEST); while not balancing "
     "(motor off) x and phi as the sensors read them and the rates 0.",
     (("x", "h", 0.0001, "m", "estimated cart position"),
      ("xdot", "h", 0.001, "m/s", "estimated cart speed"),
      ("phi", "h", 0.0001, "rad", "estimated tilt from upright"),
      ("phidot", "h", 0.001, "rad/s", "estimated tilt rate"))),
    (TELEM_CTRL, "telem_ctrl", TO_HOST,
     "Telemetry part 2: reference, command and step time of the same tick as the preceding TELEM_STATE.",
     (("ref", "h", 0.0001, "m", "cart position reference"),
      ("force", "h", 0.01, "N", "commanded cart force after saturation (0 while not balancing: what is applied)"),
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
     (("x_um", "i", 1e-6, "m", "cart position reference"),
      ("check", "I", 1, "", "CRC-32 of the id byte and x_um (integrity check)"))),
    (ARM, "arm", TO_BOARD,
     "Arm the motor (disarmed -> armed) if epoch is the board's current arming token (SESSION.token); "
     "refused (STALE_EPOCH) otherwise, and (FAULTED) while a fault is latched; a repeat while armed "
     "with the same token changes nothing and is ACKed. ACK or NACK.",
     (("epoch", "I", 1, "", "the board's arming token, read from its SESSION"),
      ("check", "I", 1, "", "CRC-32 of the id byte and epoch (integrity check)"))),
    (DISARM, "disarm", TO_BOARD,
     "Disarm: motor off, always accepted; the arming epoch changes, so no arm sent before it can act. ACK.",
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
      ("value", "i", 1, "", "new value in the parameter's unit"),
      ("check", "3s", 1, "", "low 24 bits of the CRC-32 of the id byte, index and value, little-endian "
       "(integrity check)"))),
    (PARAM_VALUE, "param_value", TO_HOST,
     "A parameter's current value (reply to PARAM_GET / PARAM_SET).",
     (("index", "B", 1, "", "parameter index"),
      ("value", "i", 1, "", "value in the parameter's unit"))),
    (GAINS_BEGIN, "gains_begin", TO_BOARD,
     "Start a gain-table upload: total length and CRC-16/CCITT-FALSE of the whole table, and the arming token "
     "(SESSION.token) of the session it belongs to: a token that is not the board's current one is refused "
     "(STALE_EPOCH), and a token change (disarm, fault, reset) ends the upload. ACK or NACK(BAD_LENGTH).",
     (("nbytes", "H", 1, "B", "table length in bytes (1..GAINS_MAX)"),
      ("crc", "H", 1, "", "CRC-16/CCITT-FALSE of the table bytes"),
      ("token", "I", 1, "", "the board's arming token (SESSION.token)"))),
    (GAINS_CHUNK, "gains_chunk", TO_BOARD,
     "Table bytes [offset, offset+6) in offset order, the last chunk zero-padded. ACK (a repeat of the previous chunk is ACKed again) or NACK(BAD_SEQUENCE, upload aborted).",
     (("offset", "H", 1, "B", "byte offset of this chunk, multiple of 6"),
      ("data", "6s", 1, "", "six table bytes"))),
    (GAINS_COMMIT, "gains_commit", TO_BOARD,
     "Check length, session, CRC-16 and CRC-32 and apply the table atomically; only while the motor is off "
     "(disarmed or fault): refused (ARMED) before any other check otherwise. ACK or NACK (old table kept).",
     (("check", "I", 1, "", "CRC-32 (zlib.crc32) of the whole table; the board compares its low 30 bits"),)),
    (REQUEST, "request", TO_BOARD,
     "Ask the board to send one message now (heartbeat, telem_state, timing, version, stats_decode: all three "
     "stats messages). Answered by that message or NACK.",
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
    (HOST_HEARTBEAT, "host_heartbeat", TO_BOARD,
     "The controlling host is alive: with SET_REFERENCE (and HIL_SENSOR) the only frames that feed the "
     "board's link watchdog (watchdog_ms); a host sends it while connected (host.link.clients.Link). No reply.",
     ()),
    (VERSION, "version", TO_HOST,
     "Identity (on REQUEST): the host refuses a board whose table_hash differs from its own.",
     (("fw_version", "B", 1, "", "firmware version major << 4 | minor (pyproject.toml)"),
      ("table_hash", "H", 1, "", "CRC-16 of the message table (ids, fields, reasons, states; firmware/identity.py)"),
      ("param_hash", "H", 1, "", "CRC-16 of the parameter table (PARAMS)"),
      ("gains_crc", "H", 1, "", "CRC-16/CCITT-FALSE of the active gain table"),
      ("reset_cause", "B", 1, "", "why the board last started (0 power-on/unknown; see the firmware's reset markers)"))),
    (STATS_DECODE, "stats_decode", TO_HOST,
     "Stats 1/3 (on REQUEST(STATS_DECODE), with STATS_FRAMES and STATS_LOOP): frames the board's decoder dropped "
     "since boot, by cause (low 16 bits, wrap).",
     (("crc", "H", 1, "", "CRC mismatch"),
      ("length", "H", 1, "", "truncated, malformed or wrong payload length"),
      ("unknown", "H", 1, "", "unknown message id"),
      ("framing", "H", 1, "", "overrun (serial), bad end marker/flags or bytes outside a frame (CAN on a stream)"))),
    (STATS_FRAMES, "stats_frames", TO_HOST,
     "Stats 2/3: frames in and out since boot (wrap at 2**30).",
     (("frames_in", "I", 1, "", "valid frames decoded"),
      ("frames_out", "I", 1, "", "frames sent before this one"))),
    (STATS_LOOP, "stats_loop", TO_HOST,
     "Stats 3/3: loop and heap since boot.",
     (("step_max_us", "H", 1, "us", "longest control step since boot"),
      ("overruns", "H", 1, "", "deadline misses since boot (saturates at 65535)"),
      ("mem_free", "H", 64, "B", "free heap in units of 64 B (saturates), sampled when the stats are sent"),
      ("gc_count", "H", 1, "", "garbage collections seen since boot (heap in use fell between two samples)"))),
    (STATS_CAN, "stats_can", TO_HOST,
     "CAN controller state (CAN link only): sent on REQUEST(STATS_CAN) and whenever the controller's error "
     "state changes (warning, passive, bus-off and back).",
     (("tec", "B", 1, "", "transmit error counter (MCP2515 TEC)"),
      ("rec", "B", 1, "", "receive error counter (MCP2515 REC)"),
      ("eflg", "B", 1, "", "error flags: 1 EWARN, 2 RXWAR, 4 TXWAR, 8 RXEP, 16 TXEP, 32 TXBO (bus-off)"),
      ("bus_off", "H", 1, "", "bus-off events since boot (wrap)"),
      ("rx_overflow", "H", 1, "", "receive buffer overflows since boot (frames lost; wrap)"),
      ("tx_dropped", "B", 1, "", "frames not sent since boot: queue full or bus-off (saturates at 255)"))),
    (SAVE_CONFIG, "save_config", TO_BOARD,
     "Save the parameters and the active gain table to flash (two copies with CRC and sequence number, "
     "loaded at boot); only while the motor is off, run between control ticks. ACK once saved, or NACK "
     "(ARMED, STORAGE; BAD_STATE while a save is queued; NOT_SUPPORTED without storage).",
     ()),
    (SENSORS_RAW, "sensors_raw", TO_HOST,
     "The sensors as the last control tick read them, before any calibration but the 16-bit counter (on "
     "REQUEST; upright board calibrate).",
     (("adc", "H", 1, "count", "angle ADC counts (after oversampling), clamped to 0..full scale"),
      ("enc", "H", 1, "count", "quadrature encoder counter (16-bit, wraps), as read"),
      ("pos", "i", 1, "count", "cart position in encoder counts since balancing started (enc_sign applied)"))),
    (MODE, "mode", TO_BOARD,
     "Switch what the board runs on its link, without a reflash: 0 robot (the paced control loop, the "
     "default at boot), 1 hil (lockstep hardware-in-the-loop: HIL_SENSOR in, HIL_ACTUATOR out, motor off), "
     "2 repl (link closed, MicroPython REPL back, e.g. for mpremote on a USB link). Only while the motor is "
     "off (disarmed or fault); ACK (then the switch) or NACK (ARMED, OUT_OF_RANGE).",
     (("mode", "B", 1, "", "0 robot, 1 hil, 2 repl"),)),
    (EXCITE, "excite", TO_BOARD,
     "Identification excitation played by the firmware (upright board excite, upright identify): a PRBS "
     "(15-bit LFSR, each bit held div ticks) of +-amp on the cart force; mode 1 adds it to the controller's "
     "force, mode 2 applies it alone, open loop (cart-only run: pendulum removed or locked), mode 0 stops. "
     "Starts only while balancing (BAD_STATE); amp at most half the gain table's force clamp and the sum "
     "clamped to it (OUT_OF_RANGE otherwise); stops by itself on disarm and on any fault. While a mode is "
     "set, TELEM_STATE x and phi are the sensors as read (not the estimate) and TELEM_CTRL force is the "
     "force applied, excitation included. ACK or NACK.",
     (("mode", "B", 1, "", "0 off, 1 added to the balancing force, 2 open loop (force = excitation)"),
      ("div", "B", 1, "tick", "control ticks per PRBS bit (1..255)"),
      ("amp_mn", "H", 0.001, "N", "amplitude (1..10000 mN)"),
      ("check", "I", 1, "", "CRC-32 of the id byte, mode, div and amp_mn (integrity check)"))),
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
R_NOT_READY = const(15)
R_STALE_EPOCH = const(16)
R_STORAGE = const(17)
R_BAD_CHECK = const(18)

REASONS = (
    (OK, "ok", "accepted"),
    (R_UNKNOWN, "unknown", "not a command the board accepts (wrong direction or unknown id)"),
    (R_OUT_OF_RANGE, "out_of_range", "a value is outside its documented range (e.g. reference beyond ref_limit_um)"),
    (R_BAD_INDEX, "bad_index", "no parameter with this index"),
    (R_READ_ONLY, "read_only", "parameter cannot be written"),
    (R_FAULTED, "faulted", "a fault is latched: clear it first (arming refused)"),
    (R_ARMED, "armed", "only allowed while the motor is off: gain commit, save, mode, and the parameters "
     "that change the drive or the sensors (DRIVE_PARAMS: signs, pot offset, max_duty, node_id)"),
    (R_BAD_STATE, "bad_state", "not allowed in the current supervisor state"),
    (R_BAD_LENGTH, "bad_length", "gain table length is 0, too long, or not the expected size"),
    (R_BAD_CRC, "bad_crc", "gain table CRC does not match the bytes received"),
    (R_BAD_SEQUENCE, "bad_sequence", "gain chunk out of order, or no upload in progress"),
    (R_INCOMPLETE, "incomplete", "commit before all gain table bytes arrived"),
    (R_BAD_SHAPE, "bad_shape", "gain table header/shape does not match the firmware"),
    (R_UNSTABLE, "unstable", "gain table rejected by the firmware's stability/finiteness check"),
    (R_NOT_SUPPORTED, "not_supported", "the board does not implement this request"),
    (R_NOT_READY, "not_ready", "arm refused: the active gain table failed its check or its CRC at boot/upload; "
     "clear_faults does not change that, only uploading a good table does"),
    (R_STALE_EPOCH, "stale_epoch", "arm or gain upload with a token that is not the board's current one: sent "
     "before a reset, disarm, clear_faults or fault, or a repeat; read SESSION.token and send again"),
    (R_STORAGE, "storage", "save_config failed: the flash filesystem refused the write (old configuration kept)"),
    (R_BAD_CHECK, "bad_check", "the integrity check (CRC-32) of a command that moves the cart, or of an uploaded "
     "table, does not match: a corrupted frame, nothing changed"),
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
P_POT_OFFSET = const(9)
P_ADC_SIGN = const(10)
P_ENC_SIGN = const(11)
P_MOTOR_SIGN = const(12)
P_GEAR_PLAY = const(13)
P_CART_COULOMB = const(14)
P_REF_RATE = const(15)
N_PARAMS = const(16)

# parameters that change the drive or what the sensors mean (signs, offsets, the duty clamp,
# the CAN node id the host reaches the board at): param_set is refused (ARMED) while armed or
# balancing -- changed under a balancing robot they tip it
DRIVE_PARAMS = (P_MAX_DUTY, P_NODE_ID, P_POT_OFFSET, P_ADC_SIGN, P_ENC_SIGN, P_MOTOR_SIGN, P_GEAR_PLAY,
                P_CART_COULOMB)

# (index, name, unit, min, max, default, doc); every value an int with |v| < 2**30
PARAMS = (
    (P_TILT_LIMIT, "tilt_limit_mrad", "mrad", 50, 1500, 500,
     "tilt beyond which the supervisor cuts the motor and latches a fault"),
    (P_WATCHDOG_MS, "watchdog_ms", "ms", 10, 10000, 250,
     "link watchdog: no host_heartbeat, set_reference or HIL sensor frame for this long while armed -> motor off, fault"),
    (P_LOOP_RATE, "loop_rate_hz", "Hz", 50, 2000, 500,
     "read-only: the control loop rate, always the active gain table's RATE (param_set is refused "
     "with read_only; the period is a safety input, see deadline faults)"),
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
    (P_POT_OFFSET, "pot_offset", "count", -1, 65535, -1,
     "angle ADC counts with the pendulum upright (upright board calibrate); -1: the gain table's "
     "(robot.toml sensors.pot_offset)"),
    (P_ADC_SIGN, "adc_sign", "", -1, 1, 1,
     "angle ADC direction: -1 flips it (0 counts as +1); start-up value firmware/board.py ADC_SIGN"),
    (P_ENC_SIGN, "enc_sign", "", -1, 1, 1,
     "encoder direction: -1 flips it (0 counts as +1); start-up value firmware/board.py ENC_SIGN"),
    (P_MOTOR_SIGN, "motor_sign", "", -1, 1, 1,
     "motor direction on top of firmware/board.py MOTOR_SIGN: -1 flips it (0 counts as +1)"),
    (P_GEAR_PLAY, "gear_play", "count", 0, 255, 0,
     "gear play between the motor's encoder and the wheels, in encoder counts (robot.toml "
     "motor.backlash; upright commission sets it): the estimator takes the wheel side half the play "
     "behind the encoder while the gear drives, its own prediction inside the play while the motor "
     "crosses it, and its predictor is given only the force the gear passes (0: no play)"),
    (P_CART_COULOMB, "cart_coulomb", "cN", 0, 1000, 0,
     "the cart's Coulomb (sliding) friction in 0.01 N (robot.toml cart.coulomb; upright commission "
     "sets it): with gear_play, the force the predictor is given against the estimated speed while "
     "the motor side crosses the play (the table's compensation acts only through the gear)"),
    (P_REF_RATE, "ref_rate_mm_s", "mm/s", 0, 5000, 0,
     "while balancing, a new set_reference moves the controller's reference to it at this speed "
     "(a ramp, not a step: the step's force demand and its gear-play engagements break the 5 m/s^2 "
     "limit; robot.toml loop.ref_rate, upright commission sets it); 0: at once"),
)

# ---- status values: read-only board figures, read with PARAM_GET(STATUS_BASE + k) ----
# answered by PARAM_VALUE like a parameter, never saved, refused by PARAM_SET (read_only);
# each an int with |v| < 2**30 (the host: host.link.clients.Link.status)
STATUS_BASE = const(64)
S_UPTIME_MS = const(0)
S_LATE = const(1)
S_LINK_DEFERRED = const(2)
S_LINK_WAIT_MAX = const(3)
S_CFG_STATUS = const(4)
S_CFG_SLOT = const(5)
S_CFG_SEQ = const(6)
S_STARTS = const(7)
N_STATUS = const(8)
# (k, name, unit, doc)
STATUS = (
    (S_UPTIME_MS, "uptime_ms", "ms", "time since the board started (not reset by a MODE switch), wraps at 2**30 ms "
     "(12.4 days); HEARTBEAT.uptime_ms is its low 16 bits"),
    (S_LATE, "late_ticks", "", "loop ticks that started late (gap > 1.5 periods) since start (saturates at 65535)"),
    (S_LINK_DEFERRED, "link_deferred", "", "host frames that waited in the receive buffer for a later tick "
     "(the link's per-tick budget was spent) since start (saturates at 65535)"),
    (S_LINK_WAIT_MAX, "link_wait_max", "tick", "longest time a host frame waited in the receive buffer, in ticks"),
    (S_CFG_STATUS, "cfg_status", "", "saved configuration at start-up: 0 loaded, 1 empty (none saved), 2 corrupt "
     "(copies there, none valid: defaults, F_CONFIG), 3 no storage, 4 migrated (a copy of an older gain-table "
     "layout: parameters kept, table converted), 5 params only (a copy of another table layout: parameters kept, "
     "the firmware's own table)"),
    (S_CFG_SLOT, "cfg_slot", "", "the saved copy in force: 0 (cfg_a.bin), 1 (cfg_b.bin), -1 none (defaults)"),
    (S_CFG_SEQ, "cfg_seq", "", "sequence number of the saved copy in force (0: none); each save writes newest + 1"),
    (S_STARTS, "starts", "", "control-loop starts since the board started: 1, +1 after each MODE switch back to "
     "the robot (the board did not reset: HEARTBEAT.boot unchanged)"),
)

# ---- fault flags (HEARTBEAT.faults; HIL_ACTUATOR.faults carries the low 8 bits) ----
# The supervisor (firmware/supervisor.py) owns the logic and the F_* constants; this table
# documents every flag (tests/test_firmware_supervisor.py: the two agree).  Sticky until
# clear_faults, which a still-present cause latches again on the next tick.
# (bit, name, doc)
FAULTS = (
    (1, "tilt", "|tilt| beyond tilt_limit_mrad while balancing (the pendulum fell)"),
    (2, "watchdog", "no host_heartbeat, set_reference or HIL sensor frame for watchdog_ms while armed/balancing"),
    (4, "adc_rail", "angle ADC at 0 or full scale: potentiometer open, shorted or unpowered"),
    (8, "enc_jump", "encoder step larger than the cart can move in one tick: noise/lost counts"),
    (16, "track", "cart beyond the track (1.25 x the reference limit) while balancing"),
    (32, "gains", "the active gain table failed its check or its CRC (boot or upload): the board "
     "is not ready and arm is refused (not_ready) until a good table is uploaded"),
    (64, "stall", "|duty| >= stall_duty beyond the table's deadband compensation for stall_ms with no encoder count while balancing"),
    (128, "loop", "the paced loop failed (an allocation with the heap locked); motor off"),
    (256, "deadline", "control deadline missed (ODrive's ERROR_CONTROL_DEADLINE_MISSED): one gap "
     "between step starts longer than 10 periods, or late ticks (gap > 1.5 periods) faster than "
     "the miss budget allows (more than 4 in a row, or more than ~1 in 25 sustained); motor off"),
    (512, "estop", "the e-stop input (board.ESTOP_PIN, active low) was asserted; motor and driver "
     "enable off in the same tick"),
    (1024, "reset", "the board restarted after its hardware watchdog fired (hung loop) or after an "
     "exception in the loop (reset_cause says which); latched at boot so the host notices"),
    (2048, "config", "saved configuration copies exist but none is valid (CRC, shape or content): "
     "defaults in force, arming refused until a gain table is uploaded (firmware/store.py)"),
    (4096, "undervolt", "motor supply (ADC1 through the divider, filtered) below vsup_min_mv while armed "
     "or balancing"),
    (8192, "adc_open", "angle potentiometer wiper open: the periodic pad-pull test moved the reading "
     "most of the way to the rail (docs/firmware.md, wiring)"),
    (16384, "can", "CAN link (firmware/link_can.py): the MCP2515 did not answer at start-up (wiring), or the "
     "controller went bus-off; latched again on every tick while the bus is off, so it clears only once the "
     "bus has recovered and the host sends clear_faults"),
)

# ---- reset causes (the firmware's own marker in a WATCHDOG scratch register; App.reset_cause) ----
RC_POWER_ON = const(0)
RC_WATCHDOG = const(1)
RC_EXCEPTION = const(2)
# (value, name, doc)
RESET_CAUSES = (
    (RC_POWER_ON, "power_on", "power-on, reset pin, or a clean restart (no marker left by the loop)"),
    (RC_WATCHDOG, "watchdog", "the hardware watchdog reset the board: the control loop stopped feeding it (hung)"),
    (RC_EXCEPTION, "exception", "an exception escaped the control loop: motor off, fault reported, board reset"),
)
