# The per-tick code of Sensors, Supervisor, Motor, Timing, Pacer, App._supply and App.step
# compiled by MicroPython's viper emitter: App(config={"emitter": "viper"}) builds these
# subclasses instead of the plain ones (firmware/board.py EMITTER: the board's default; the
# serial link builds PacerV) and runs StepV.step as its step().  Same attributes, same
# results: tests/test_firmware_fasttick.py compares the methods with the plain ones on
# random and extreme inputs, and whole Apps tick by tick, under the unix port's viper and
# under CPython.
#
# Why the state lives in int32 arrays: on a 125 MHz M0+ (emulated cycles) an attribute load
# or store costs about 2.5 us even in viper (an instance-dict lookup), a ptr32 load a few
# cycles, a call 4-9 us.  So the hot attributes of SensorsV, SupervisorV, MotorV and TimingV
# are slots of one array('i') per object (_S), visible to the rest of the firmware as the
# same attribute names through properties (cold paths: commands, reports); the per-tick
# work is in module-level viper functions on those arrays (sensors_update, supervisor_update,
# motor_duty, timing_begin/end), which the methods and StepV.step call.  Every slot holds a
# value the plain classes keep small (|v| < 2**30); flags are 0/1 slots read as bools.
# Under CPython the decorator is a no-op and ptr32 the array itself.  The WebAssembly port
# has no native emitter: import this module only when selected (as fastpath.py /
# fastframe.py).
#
# Viper rules kept here: module constants are local const()s (a plain global is an
# object: no native arithmetic with it), big literals never take part in arithmetic, every
# value stays a small int as in the plain methods (the products are bounded the same way).
# On a 64-bit port a ptr32 load is zero-extended: a slot that can be negative is read as
# ((S[i] + sb) & msk) - sb (fastpath.py's sign extension; a no-op on 32 bits).

try:
    import micropython
    from micropython import const
except ImportError:  # CPython
    class micropython:
        @staticmethod
        def viper(f):
            return f

    def const(x):
        return x

    def ptr32(a):
        return a

from array import array

from .motor import Motor
from .pacer import Pacer
from .sensors import Sensors
from .supervisor import Supervisor
from .timing import Timing

# supervisor states and flags (== supervisor.py's; the test checks)
_DISARMED = const(0)
_ARMED = const(1)
_BALANCING = const(2)
_FAULT = const(3)
_F_TILT = const(1)
_F_WATCHDOG = const(2)
_F_ADC_RAIL = const(4)
_F_ENC_JUMP = const(8)
_F_TRACK = const(16)
_F_GAINS = const(32)
_F_STALL = const(64)
_F_ESTOP = const(512)
_F_UNDERVOLT = const(4096)
_F_ADC_OPEN = const(8192)
CONSTS = {"ARMED": _ARMED, "BALANCING": _BALANCING, "FAULT": _FAULT, "F_TILT": _F_TILT, "F_WATCHDOG": _F_WATCHDOG,
          "F_ADC_RAIL": _F_ADC_RAIL, "F_ENC_JUMP": _F_ENC_JUMP, "F_TRACK": _F_TRACK, "F_GAINS": _F_GAINS,
          "F_STALL": _F_STALL, "F_UNDERVOLT": _F_UNDERVOLT, "F_ESTOP": _F_ESTOP, "F_ADC_OPEN": _F_ADC_OPEN,
          "DISARMED": _DISARMED}
# msgtable parameter indices (== msgtable's; the test checks)
_P_TELEM_DIV = const(5)
_P_HEARTBEAT_MS = const(6)
PARAMS = {"P_TELEM_DIV": _P_TELEM_DIV, "P_HEARTBEAT_MS": _P_HEARTBEAT_MS}
_POS_MAX = const(0x3FFFFF)  # sensors.py
_VS_ONE = const(4096)  # motor.py
_D_PRE = const(65535)
_U16 = const(65535)  # timing.py
_TICKS_MASK = const(0x3FFFFFFF)  # fixmath.ticks_diff, written out: no call
_TICKS_HALF = const(0x20000000)
_TICKS_HIGH = const(-0x40000000)

# the slots of each class's _S (attribute name -> index; FIELDS for the test)
_SN_ADC_MAX = const(0)
_SN_POT = const(1)
_SN_ADC_SIGN = const(2)
_SN_COUNTS = const(3)
_SN_YLP = const(4)
_SN_YP = const(5)
_SN_QP = const(6)
_SN_PRIMED = const(7)
_SN_LAST = const(8)
_SN_ENC_SIGN = const(9)
_SN_DELTA = const(10)
_SN_ENCJ = const(11)
_SN_JUMP = const(12)
_SN_POS = const(13)
_SN_YLX = const(14)
_SN_YX = const(15)
_SN_QX = const(16)
_SN_RAIL = const(17)
_SN_N = const(18)
_SU_STATE = const(0)
_SU_FAULTS = const(1)
_SU_LAST = const(2)
_SU_TILT = const(3)
_SU_ARM = const(4)
_SU_TRACK = const(5)
_SU_WD_TICKS = const(6)
_SU_WD_COUNT = const(7)
_SU_STALL_TICKS = const(8)
_SU_STALL_DUTY = const(9)
_SU_STALL_COUNT = const(10)
_SU_READY = const(11)
_SU_N = const(12)
_MO_BACKEMF = const(0)
_MO_MAX_DUTY = const(1)
_MO_VSCALE = const(2)
_MO_KDU = const(3)
_MO_KDV = const(4)
_MO_SD = const(5)
_MO_HALF = const(6)
_MO_DEADBAND = const(7)
_MO_N = const(8)
_TM_PERIOD = const(0)
_TM_MEAN = const(1)
_TM_WORST = const(2)
_TM_MISSES = const(3)
_TM_STEP_MAX = const(4)
_TM_OVERRUNS = const(5)
_TM_STEP_MIN = const(6)
_TM_PERIOD_MAX = const(7)
_TM_JITTER_MAX = const(8)
_TM_STEPS = const(9)
_TM_SUM = const(10)
_TM_N = const(11)
_TM_LAST_US = const(12)
_TM_HAVE_LAST = const(13)
_TM_SLOTS = const(14)


def _int(i):
    # an int attribute kept in slot i of self._S
    def get(self):
        return self._S[i]

    def put(self, v):
        self._S[i] = v

    return property(get, put)


def _flag(i):
    # a bool attribute kept in slot i of self._S (0/1)
    def get(self):
        return self._S[i] != 0

    def put(self, v):
        self._S[i] = 1 if v else 0

    return property(get, put)


def _slots(n):
    return array("i", bytes(4 * n))


@micropython.viper
def sensors_update(S: ptr32, adc: int, enc: int):
    # Sensors.update on a SensorsV's slots
    sb = 1
    sb = sb << 31
    msk = sb | (sb - 1)
    am = ((S[_SN_ADC_MAX] + sb) & msk) - sb
    if adc <= 0:
        adc = 0
        S[_SN_RAIL] = 1
    elif adc >= am:
        adc = am
        S[_SN_RAIL] = 1
    else:
        S[_SN_RAIL] = 0
    c = adc - (((S[_SN_POT] + sb) & msk) - sb)
    if ((S[_SN_ADC_SIGN] + sb) & msk) - sb < 0:
        c = -c
    S[_SN_COUNTS] = c
    lim = ((S[_SN_YLP] + sb) & msk) - sb
    if c > lim:
        c = lim
    elif c < -lim:
        c = -lim
    S[_SN_YP] = c << S[_SN_QP]
    enc = enc & 0xFFFF
    dl = 0
    if S[_SN_PRIMED]:
        dl = (enc - S[_SN_LAST]) & 0xFFFF
        if dl >= 0x8000:
            dl -= 0x10000
    else:
        S[_SN_PRIMED] = 1
    S[_SN_LAST] = enc
    if ((S[_SN_ENC_SIGN] + sb) & msk) - sb < 0:
        dl = -dl
    S[_SN_DELTA] = dl
    j = ((S[_SN_ENCJ] + sb) & msk) - sb
    if dl > j or dl < -j:
        S[_SN_JUMP] = 1
    else:
        S[_SN_JUMP] = 0
    v = (((S[_SN_POS] + sb) & msk) - sb) + dl
    if v > _POS_MAX:
        v = _POS_MAX
    elif v < -_POS_MAX:
        v = -_POS_MAX
    S[_SN_POS] = v
    lim = ((S[_SN_YLX] + sb) & msk) - sb
    if v > lim:
        v = lim
    elif v < -lim:
        v = -lim
    S[_SN_YX] = v << S[_SN_QX]


class SensorsV(Sensors):
    adc_max = _int(_SN_ADC_MAX)
    pot_offset = _int(_SN_POT)
    adc_sign = _int(_SN_ADC_SIGN)
    counts = _int(_SN_COUNTS)
    ylp = _int(_SN_YLP)
    yp = _int(_SN_YP)
    qp = _int(_SN_QP)
    primed = _flag(_SN_PRIMED)
    last = _int(_SN_LAST)
    enc_sign = _int(_SN_ENC_SIGN)
    delta = _int(_SN_DELTA)
    encj = _int(_SN_ENCJ)
    jump = _flag(_SN_JUMP)
    pos = _int(_SN_POS)
    ylx = _int(_SN_YLX)
    yx = _int(_SN_YX)
    qx = _int(_SN_QX)
    rail = _flag(_SN_RAIL)

    def __init__(self, t, off, adc_sign=1, enc_sign=1, pot_offset=None):
        self._S = _slots(_SN_N)
        Sensors.__init__(self, t, off, adc_sign, enc_sign, pot_offset)

    def update(self, adc, enc):
        sensors_update(self._S, adc, enc)


@micropython.viper
def supervisor_update(U: ptr32, counts: int, pos: int, rail: int, jump: int, delta: int, duty: int, ext: int,
                      tok: int) -> int:
    # Supervisor.update on a SupervisorV's slots (tok: its timing_ok, read only when ARMED);
    # returns 1 on the tick balancing starts
    sb = 1
    sb = sb << 31
    msk = sb | (sb - 1)
    f = ext
    if not U[_SU_READY]:
        f |= _F_GAINS
    if rail:
        f |= _F_ADC_RAIL
    if jump:
        f |= _F_ENC_JUMP
    st = U[_SU_STATE]
    if st == _BALANCING:
        t = ((U[_SU_TILT] + sb) & msk) - sb
        if not rail and (counts > t or counts < -t):
            f |= _F_TILT
        t = ((U[_SU_TRACK] + sb) & msk) - sb
        if pos > t or pos < -t:
            f |= _F_TRACK
        if ((U[_SU_STALL_TICKS] + sb) & msk) - sb > 0:
            if delta != 0:
                U[_SU_STALL_COUNT] = 0
            else:
                t = ((U[_SU_STALL_DUTY] + sb) & msk) - sb
                if duty >= t or duty <= -t:
                    n = U[_SU_STALL_COUNT] + 1
                    U[_SU_STALL_COUNT] = n
                    if n > ((U[_SU_STALL_TICKS] + sb) & msk) - sb:
                        f |= _F_STALL
    if (st == _ARMED or st == _BALANCING) and ((U[_SU_WD_TICKS] + sb) & msk) - sb > 0:
        n = U[_SU_WD_COUNT] + 1
        U[_SU_WD_COUNT] = n
        if n > ((U[_SU_WD_TICKS] + sb) & msk) - sb:
            f |= _F_WATCHDOG
    U[_SU_LAST] = f
    if f:
        U[_SU_FAULTS] = U[_SU_FAULTS] | f
        U[_SU_STATE] = _FAULT
        return 0
    if U[_SU_FAULTS]:
        U[_SU_STATE] = _FAULT
        return 0
    if st == _ARMED and tok:
        t = ((U[_SU_ARM] + sb) & msk) - sb
        if counts > -t and counts < t:
            U[_SU_STATE] = _BALANCING
            U[_SU_STALL_COUNT] = 0
            return 1
    return 0


class SupervisorV(Supervisor):
    # timing_ok stays an attribute: App.run reads it every tick, the update only when ARMED
    state = _int(_SU_STATE)
    faults = _int(_SU_FAULTS)
    last = _int(_SU_LAST)
    tilt_counts = _int(_SU_TILT)
    arm_counts = _int(_SU_ARM)
    track_counts = _int(_SU_TRACK)
    wd_ticks = _int(_SU_WD_TICKS)
    wd_count = _int(_SU_WD_COUNT)
    stall_ticks = _int(_SU_STALL_TICKS)
    stall_duty = _int(_SU_STALL_DUTY)
    stall_count = _int(_SU_STALL_COUNT)
    ready = _flag(_SU_READY)

    def __init__(self):
        self._S = _slots(_SU_N)
        Supervisor.__init__(self)

    def update(self, counts, pos, rail, jump, delta, duty, ext):
        # every argument given (App.step passes all seven)
        return supervisor_update(self._S, counts, pos, 1 if rail else 0, 1 if jump else 0, delta, duty, ext,
                                 1 if self.timing_ok else 0) != 0


@micropython.viper
def motor_duty(M: ptr32, u: int, vh: int) -> int:
    # Motor.duty on a MotorV's slots
    sb = 1
    sb = sb << 31
    msk = sb | (sb - 1)
    acc = (((M[_MO_KDU] + sb) & msk) - sb) * u + (((M[_MO_HALF] + sb) & msk) - sb)
    if M[_MO_BACKEMF]:
        acc += (((M[_MO_KDV] + sb) & msk) - sb) * vh
    d = acc >> M[_MO_SD]
    db = ((M[_MO_DEADBAND] + sb) & msk) - sb
    # in the direction of the duty (the bridge takes its deadband off |duty|: with the
    # back-EMF term the duty can oppose the force), of the force when the duty is 0
    if d > 0 or (d == 0 and u > 0):
        d += db
    elif d < 0 or u < 0:
        d -= db
    vs = ((M[_MO_VSCALE] + sb) & msk) - sb
    if vs != _VS_ONE:
        if d > _D_PRE:
            d = _D_PRE
        elif d < -_D_PRE:
            d = -_D_PRE
        d = (d * vs + 2048) >> 12
    lim = ((M[_MO_MAX_DUTY] + sb) & msk) - sb
    if d > lim:
        return lim
    if d < -lim:
        return -lim
    return d


class MotorV(Motor):
    backemf = _flag(_MO_BACKEMF)
    max_duty = _int(_MO_MAX_DUTY)
    vscale = _int(_MO_VSCALE)
    kdu = _int(_MO_KDU)
    kdv = _int(_MO_KDV)
    sd = _int(_MO_SD)
    half = _int(_MO_HALF)
    deadband = _int(_MO_DEADBAND)

    def __init__(self, t, off, deadband=None, backemf=True):
        self._S = _slots(_MO_N)
        Motor.__init__(self, t, off, deadband, backemf)

    def duty(self, u, vh):
        return motor_duty(self._S, u, vh)


@micropython.viper
def timing_begin(M: ptr32, t: int):
    # Timing.begin on a TimingV's slots, the tick difference written out (fixmath.ticks_diff:
    # the same values for a clock whose period is a multiple of 2**30)
    sb = 1
    sb = sb << 31
    msk = sb | (sb - 1)
    if M[_TM_HAVE_LAST]:
        per = (t - M[_TM_LAST_US]) & _TICKS_MASK
        if per >= _TICKS_HALF:
            per |= _TICKS_HIGH
        if per > ((M[_TM_PERIOD_MAX] + sb) & msk) - sb:
            M[_TM_PERIOD_MAX] = per
        p = ((M[_TM_PERIOD] + sb) & msk) - sb
        j = per - p
        if j < 0:
            j = -j
        if j > ((M[_TM_JITTER_MAX] + sb) & msk) - sb:
            M[_TM_JITTER_MAX] = j
        if per > p + (p >> 1):
            n = M[_TM_OVERRUNS]
            if n < _U16:
                M[_TM_OVERRUNS] = n + 1
    M[_TM_LAST_US] = t
    M[_TM_HAVE_LAST] = 1


@micropython.viper
def timing_end(M: ptr32, t0: int, t1: int) -> int:
    # Timing.end on a TimingV's slots
    sb = 1
    sb = sb << 31
    msk = sb | (sb - 1)
    ex = (t1 - t0) & _TICKS_MASK
    if ex >= _TICKS_HALF:
        ex |= _TICKS_HIGH
    if ex < 0:
        ex = 0
    if ex < ((M[_TM_STEP_MIN] + sb) & msk) - sb:
        M[_TM_STEP_MIN] = ex
    if ex > ((M[_TM_STEP_MAX] + sb) & msk) - sb:
        M[_TM_STEP_MAX] = ex
    if ex > ((M[_TM_PERIOD] + sb) & msk) - sb:
        n = M[_TM_OVERRUNS]
        if n < _U16:
            M[_TM_OVERRUNS] = n + 1
    n = M[_TM_STEPS]
    if n < _U16:
        M[_TM_STEPS] = n + 1
    if ex > _U16:
        ex = _U16
    s = M[_TM_SUM] + ex
    n = M[_TM_N] + 1
    if n >= 1024:
        M[_TM_MEAN] = s >> 10
        s = 0
        n = 0
    M[_TM_SUM] = s
    M[_TM_N] = n
    return ex


class TimingV(Timing):
    period_us = _int(_TM_PERIOD)
    mean_us = _int(_TM_MEAN)
    worst = _int(_TM_WORST)
    misses = _int(_TM_MISSES)
    step_max = _int(_TM_STEP_MAX)
    overruns = _int(_TM_OVERRUNS)
    step_min = _int(_TM_STEP_MIN)
    period_max = _int(_TM_PERIOD_MAX)
    jitter_max = _int(_TM_JITTER_MAX)
    steps = _int(_TM_STEPS)
    _sum = _int(_TM_SUM)
    _n = _int(_TM_N)
    last_us = _int(_TM_LAST_US)
    _have_last = _flag(_TM_HAVE_LAST)

    def __init__(self, period_us, diff=None):
        self._S = _slots(_TM_SLOTS)
        Timing.__init__(self, period_us, diff)

    def begin(self, t):
        timing_begin(self._S, t)

    def end(self, t0, t1):
        return timing_end(self._S, t0, t1)


class StepV:
    # App.step for the viper emitter (App sets app.step = StepV(app).step): the same
    # statements in the same order as App.step, the sensors, supervisor, motor and timing
    # on their slot arrays (the functions above), the app's own state and hooks read from
    # the app as App.step reads them (a test may replace app._read_enc); the rare branches
    # (start of balancing, the excitation, the driver enable, e-stop, supply, wiper test)
    # call the app's methods
    def __init__(self, app):
        self.app = app
        self.hal = app.hal
        self.s = app.sensors
        self.sup = app.sup
        self.ctrl = app.ctrl
        self.exc = app.exc
        self.sn = app.sensors._S
        self.su = app.sup._S
        self.mo = app.motor._S
        self.tm = app.timing._S
        # what the HAL offers (fixed at App construction, as App.step's tests of it)
        self.opts = ((1 if app._has_frames else 0) | (2 if app._estop is not None else 0)
                     | (4 if app._has_open else 0) | (8 if app._read_vsup is not None else 0))

    @micropython.viper
    def step(self) -> int:
        sb = 1
        sb = sb << 31
        msk = sb | (sb - 1)
        app = self.app
        ticks = app._ticks
        t0 = int(ticks())
        # the arrays go to the functions as objects (a pointer would be boxed as an int:
        # a big one on a 64-bit port), read here through ptr32 views
        tmo = self.tm
        timing_begin(tmo, t0)
        sno = self.sn
        sensors_update(sno, int(app._read_adc()), int(app._read_enc()))
        sn = ptr32(sno)
        suo = self.su
        su = ptr32(suo)
        opts = int(self.opts)
        if opts & 1:
            n = int(self.hal.n_sensor)
            if n != int(app._frames):
                app._frames = n
                su[_SU_WD_COUNT] = 0
        ext = int(app._ext)
        if ext:
            app._ext = 0
        if opts & 2:
            if app._estop():
                ext |= _F_ESTOP
        if opts & 4:
            if self.hal.adc_open:
                ext |= _F_ADC_OPEN
        if opts & 8:
            ext |= int(app._supply(su[_SU_STATE]))
        tok = 1
        if su[_SU_STATE] == _ARMED:
            tok = 1 if self.sup.timing_ok else 0
        start = supervisor_update(suo, ((sn[_SN_COUNTS] + sb) & msk) - sb, ((sn[_SN_POS] + sb) & msk) - sb,
                                  sn[_SN_RAIL], sn[_SN_JUMP], ((sn[_SN_DELTA] + sb) & msk) - sb, int(app.duty),
                                  ext, tok)
        st = su[_SU_STATE]
        if st != int(app._st):
            if st == _FAULT:
                app._new_token()
            app._st = st
        duty = 0
        if st == _BALANCING:
            c = self.ctrl
            if start:
                self.s.zero()
                c.reset(((sn[_SN_YX] + sb) & msk) - sb, ((sn[_SN_YP] + sb) & msk) - sb)
            # Controller.schedule's common case written out (not catching, no ramp, the
            # prediction inside phi_on: the reference as set); otherwise the call
            r = app.ref
            if c.catching or c.ramp:
                r = c.schedule(r)
            else:
                on = int(c.phi_on)
                if on > 0:
                    ph = ((ptr32(c.p)[2] + sb) & msk) - sb
                    if ph > on or ph < -on:
                        r = c.schedule(r)
            u = int(app._cstep(c, ((sn[_SN_YX] + sb) & msk) - sb, ((sn[_SN_YP] + sb) & msk) - sb, r))
            duty = int(motor_duty(self.mo, u, int(c.vh)))
            if self.exc.on:
                duty = int(app._excite(c, u))
            if not app._en:
                app._drive(1)
            app._set_motor(duty)
        else:
            app._set_motor(0)
            if app._en:
                app._drive(0)
            self.exc.on = 0
        app.duty = duty
        k = int(app.tick)
        app.tick = k + 1 if k < _TICKS_MASK else 0
        f = int(app._us_frac) + int(app.period_us)
        if f >= 1000:
            k = int(app.uptime_ms)
            while f >= 1000:
                f -= 1000
                k = k + 1 if k < _TICKS_MASK else 0
            app.uptime_ms = k
        app._us_frac = f
        ex = int(timing_end(tmo, t0, int(ticks())))
        app.step_us = ex
        return duty


class PacerV(Pacer):
    # Pacer.tick on the app's int32 params array (link_serial.SerialLink builds this for an
    # app with the viper emitter and a params array: Pacer._p set)
    @micropython.viper
    def tick(self):
        p = ptr32(self._p)
        div = p[_P_TELEM_DIV]
        hb = p[_P_HEARTBEAT_MS]
        sent = 0
        if div > 0:
            n = int(self._telem_left) - 1
            if n <= 0:
                n = div
                q = (int(self.seq) + 1) & 0xFF
                self.seq = q
                self.telemetry(q)
                if div > 1:
                    sent = 1
            self._telem_left = n
        if hb <= 0:
            return
        t = int(self._hb_us) + int(self.app.period_us)
        if t < hb * 1000 or sent:
            self._hb_us = t
            return
        self._hb_us = 0
        q = (int(self.seq) + 1) & 0xFF
        self.seq = q
        self.heartbeat(q)


class SupplyV:
    # App._supply in viper: App(config={"emitter": "viper"}) with a HAL that measures the
    # supply calls SupplyV(app).update in its place (the same state, kept on the app)
    def __init__(self, app):
        self.app = app
        self.read = app._read_vsup
        self.motor = app.motor

    @micropython.viper
    def update(self, st: int) -> int:
        app = self.app
        v = int(self.read())
        a = int(app._vsup_acc)
        if a < 0:
            a = v << 3
        else:
            a += v - (a >> 3)
        app._vsup_acc = a
        v = a >> 3
        if v != int(app.vsup_mv):
            app.vsup_mv = v
            self.motor.set_supply(v, app.vsup_nom)
        if v < int(app.vsup_min) and (st == _ARMED or st == _BALANCING):
            return _F_UNDERVOLT
        return 0
