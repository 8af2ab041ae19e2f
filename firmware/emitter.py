# The code emitter, chosen in one place: which build of the hot code every part runs.
# App config "emitter" (firmware/board.py EMITTER on a board: robot mode, HIL mode and the
# unix-port HIL alike, firmware/main_hil.py) picks one of
#   "bytecode"  the plain classes and methods (any port; the WebAssembly port has no native
#               emitter, so the fast modules are imported only when selected)
#   "native"    Controller.step and the frame encoder native-compiled (fastpath.py, fastframe.py)
#   "viper"     every per-tick part in viper: the controller step (fastpath.py), the sensors,
#               supervisor, motor and timing on slot arrays, the supply filter, the whole
#               step and the link's pacer (fasttick.py), the frame encoder (fastframe.py),
#               the telemetry scaling and the commands' CRC-32 (fastlink.py)
# fastpath.py, fasttick.py, fastframe.py, fastlink.py and fastcan.py are generated from the
# plain code (host/boards/fwgen); the tests compare every build with the plain one
# (tests/test_firmware_fast*.py, test_proto_fastframe.py, test_fwgen.py).
# Start-up only: nothing here runs per tick.

EMITTERS = ("bytecode", "native", "viper")


def check(em):
    # the config value, or a one-line error naming the key
    if em not in EMITTERS:
        raise ValueError("config emitter: %r is none of bytecode, native, viper" % (em,))
    return em


def parts(em):
    # (Sensors, Motor, Supervisor, Timing, controller step function) of this emitter
    if em == "viper":
        from .fastpath import step_viper
        from .fasttick import MotorV, SensorsV, SupervisorV, TimingV
        return SensorsV, MotorV, SupervisorV, TimingV, step_viper
    from .controller import Controller
    from .motor import Motor
    from .sensors import Sensors
    from .supervisor import Supervisor
    from .timing import Timing
    cstep = Controller.step
    if em == "native":
        from .fastpath import step_native as cstep
    return Sensors, Motor, Supervisor, Timing, cstep


def telemetry(em):
    # the telemetry scaling's fast build (App.fill_telemetry), or None: the plain loop
    if em == "viper":
        from .fastlink import telem_viper
        return telem_viper
    return None


def supply(app):
    # App._supply of this emitter (a HAL that measures the supply: app._read_vsup set)
    if app.emitter == "viper":
        from .fasttick import SupplyV
        return SupplyV(app).update
    return app._supply


def step(app):
    # App.step of this emitter (the bound method the loop calls)
    if app.emitter == "viper":
        from .fasttick import StepV
        return StepV(app).step
    return app.step


def frame_encoder(em):
    # framing.Encoder's one-call build: (make_lut, encode, set_vals_len), or None: bytecode
    if em == "viper" or em == "native":
        from . import fastframe
        return (fastframe.make_lut, fastframe.encode_viper if em == "viper" else fastframe.encode_native,
                fastframe.set_vals_len)
    return None


def command_crc(em):
    # commands.Dispatcher.crc30: the integrity check's CRC-32 build, or None: crc32.py
    if em == "viper":
        from .fastlink import crc32_low30
        return crc32_low30
    return None


def pacer(app, disp):
    # the link's periodic sender (firmware/pacer.py) of the app's emitter
    # (App.params: its int32 parameter array, read directly by the pacer's tick)
    if app.emitter == "viper":
        from .fasttick import PacerV
        return PacerV(app, disp, app.params)
    from .pacer import Pacer
    return Pacer(app, disp, app.params)
