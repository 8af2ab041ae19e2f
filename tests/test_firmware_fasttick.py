"""The viper builds of the per-tick methods (firmware/fasttick.py) equal the plain ones.

SensorsV.update, SupervisorV.update, MotorV.duty, TimingV.begin/end, PacerV.tick and
SupplyV.update against Sensors/Supervisor/Motor/Timing/Pacer and App._supply on the same
pseudo-random and extreme inputs (rails, encoder wraps, every supervisor state,
watchdog/stall/tilt/track limits, supply scaling and undervoltage, tick-clock wraps, telemetry
dividers and heartbeats): every result and every attribute after every call.  Under the
MicroPython unix port (real viper code), on the emulated RP2040 (the armv6m build, a tenth of
the iterations) and under CPython (the decorator a no-op): one test body, conftest's ``interp``.
A whole App with the viper emitter builds these classes and steps allocation-free.
"""

from __future__ import annotations

import pytest

import fwharness as H
from host.boards.mpyrun import run_unix

SCRIPT = r"""
DIV = 1  # iterations / DIV (the emulated board: METHODS_DIV)
from firmware import gains as G
from firmware.controller import Controller
from firmware.sensors import Sensors
from firmware.supervisor import Supervisor
from firmware.motor import Motor
from firmware.timing import Timing
from firmware import fasttick as F
from firmware import supervisor as SV

seed = [12345]
def rnd(n):
    # deterministic LCG (the same sequence on both interpreters): 0 .. n-1
    seed[0] = (seed[0] * 1103515245 + 12345) & 0x7FFFFFFF
    return (seed[0] >> 8) % n

def pick(a):
    return a[rnd(len(a))]

flat = G.FLAT
off = Controller(G.LAYOUT, flat).off
bad = {}
def chk(name, a, b, attrs):
    for k in attrs:
        if getattr(a, k) != getattr(b, k):
            bad[name] = bad.get(name, 0) + 1
            if bad[name] < 4:
                print('diff', name, k, getattr(a, k), getattr(b, k))

cbad = 0
for k in F.CONSTS:
    if getattr(SV, k) != F.CONSTS[k]:
        cbad += 1
print('consts_bad', cbad)

# sensors
SA = ('rail', 'counts', 'yp', 'last', 'primed', 'delta', 'jump', 'pos', 'yx', 'wpos')
n = 0
for cfg in ((1, 1, 0), (-1, 1, 9), (1, -1, 0), (-1, -1, 3)):  # (adc_sign, enc_sign, gear play / 2)
    a = Sensors(flat, off, cfg[0], cfg[1])
    b = F.SensorsV(flat, off, cfg[0], cfg[1])
    a.play = b.play = cfg[2]
    enc = 65000
    for i in range(1500 // DIV):
        r = rnd(20)
        if r == 0:
            adc = pick((-5, 0, 1, 4094, 4095, 4096, 5000))
        else:
            adc = a.pot_offset + rnd(1601) - 800
        if r == 1:
            enc = rnd(65536)
        elif r == 2:
            enc = enc + pick((40000, -40000, 32767, -32768, 100000))
        else:
            enc = enc + rnd(61) - 30
        if r == 3:
            a.zero()
            b.zero()
        if r == 4:  # a pause of the loop between ticks (a save): the counts followed, no jump check
            enc = enc + rnd(4001) - 2000
            a.follow(enc)
            b.follow(enc)
            enc = enc + rnd(61) - 30
        a.update(adc, enc)
        b.update(adc, enc)
        chk('sensors', a, b, SA)
        n += 1
    # pos saturation
    a.pos = b.pos = 0x3FFFF0
    for i in range(40):
        enc += 30000
        a.update(2048, enc)
        b.update(2048, enc)
        chk('sensors', a, b, SA)
print('sensors_n', n)

# supervisor
UA = ('state', 'faults', 'last', 'wd_count', 'stall_count')
n = 0
a = Supervisor()
b = F.SupervisorV()
for s in (a, b):
    s.tilt_counts = 300
    s.arm_counts = 40
    s.track_counts = 5000
    s.wd_ticks = 50
    s.stall_ticks = 30
    s.stall_duty = 800
for i in range(20000 // DIV):
    r = rnd(40)
    if r == 0:
        st = rnd(4)
        a.state = st
        b.state = st
    elif r == 1:
        a.faults = 0
        b.faults = 0
    elif r == 2:
        v = pick((True, False))
        a.ready = v
        b.ready = v
    elif r == 3:
        v = pick((True, False))
        a.timing_ok = v
        b.timing_ok = v
    elif r == 4:
        a.feed()
        b.feed()
    elif r == 5:
        v = pick((0, 5, 50))
        a.wd_ticks = b.wd_ticks = v
        v = pick((0, 3, 30))
        a.stall_ticks = b.stall_ticks = v
    counts = pick((0, 39, 40, -40, -39, 299, 300, 301, -300, -301)) if rnd(3) == 0 else rnd(701) - 350
    pos = pick((0, 4999, 5000, 5001, -5000, -5001)) if rnd(3) == 0 else rnd(12001) - 6000
    rail = rnd(30) == 0
    jump = rnd(30) == 0
    delta = 0 if rnd(2) else rnd(21) - 10
    duty = pick((0, 799, 800, -800, -799, 32767, -32767))
    ext = pick((0, 0, 0, 0, 2048, 4096, 8192))
    ra = a.update(counts, pos, rail, jump, delta, duty, ext)
    rb = b.update(counts, pos, rail, jump, delta, duty, ext)
    if ra != rb:
        bad['sup_ret'] = bad.get('sup_ret', 0) + 1
    chk('supervisor', a, b, UA)
    n += 1
print('sup_n', n)

# motor
n = 0
for backemf in (True, False):
    a = Motor(flat, off, None, backemf)
    b = F.MotorV(flat, off, None, backemf)
    for i in range(4000 // DIV):
        if rnd(50) == 0:
            mv = pick((0, -1, 3000, 9000, 12000, 12001, 15000, 60000))
            a.set_supply(mv, 12000)
            b.set_supply(mv, 12000)
        if rnd(50) == 0:
            m = pick((32767, 20000, 100))
            a.max_duty = b.max_duty = m
        u = pick((0, 1, -1, 2000, -2000)) if rnd(4) == 0 else rnd(4001) - 2000
        vh = rnd(20001) - 10000
        if a.duty(u, vh) != b.duty(u, vh):
            bad['motor'] = bad.get('motor', 0) + 1
        n += 1
print('motor_n', n)

# timing: the clock wraps at 2**30 (step and period across the wrap)
TA = ('period_max', 'jitter_max', 'overruns', 'last_us', 'step_min', 'step_max', 'steps', 'mean_us', 'worst', 'misses')
n = 0
a = Timing(2000)
b = F.TimingV(2000)
t = 0x3FFFFFFF - 300000
for i in range(6000 // DIV):
    r = rnd(200)
    t = (t + pick((2000, 2000, 1999, 2001, 2500, 3001, 3500, 40000))) & 0x3FFFFFFF
    ex = pick((300, 700, 1200, 1999, 2000, 2001, 2600, 70000)) if rnd(5) == 0 else 500 + rnd(200)
    t1 = (t + ex) & 0x3FFFFFFF
    if r == 0:
        t1 = (t - 5) & 0x3FFFFFFF  # a clock read out of order
    a.begin(t)
    b.begin(t)
    if a.end(t, t1) != b.end(t, t1):
        bad['timing_ret'] = bad.get('timing_ret', 0) + 1
    if r == 1:
        a.reset()
        b.reset()
    chk('timing', a, b, TA)
    n += 1
print('timing_n', n)

# pacer: telemetry and heartbeat ticks and sequence numbers over every divider/heartbeat
from array import array
from firmware.pacer import Pacer
from firmware import msgtable as MT
for k in F.PARAMS:
    if getattr(MT, k) != F.PARAMS[k]:
        cbad += 1
print('consts_bad2', cbad)
class Rec:
    def __init__(self):
        self.sent = []
    def send_telemetry(self, seq):
        self.sent.append(seq)
    def send_heartbeat(self, seq):
        self.sent.append(-seq)
class App1:
    def __init__(self):
        self.params = array('i', [0] * MT.N_PARAMS)
        self.period_us = 2000
n = 0
for div, hb, per in ((10, 100, 2000), (1, 100, 2000), (0, 100, 1000), (7, 0, 2000), (3, 20, 20000), (0, 0, 2000)):
    ap = App1()
    ap.params[MT.P_TELEM_DIV] = div
    ap.params[MT.P_HEARTBEAT_MS] = hb
    ap.period_us = per
    ra, rb = Rec(), Rec()
    a, b = Pacer(ap, ra, ap.params), F.PacerV(ap, rb, ap.params)
    for i in range(700 // DIV):
        a.tick()
        b.tick()
        n += 1
    if ra.sent != rb.sent or a.seq != b.seq or a._hb_us != b._hb_us or a._telem_left != b._telem_left:
        bad['pacer'] = bad.get('pacer', 0) + 1
print('pacer_n', n)

# supply: App._supply against SupplyV(app).update on two apps fed the same readings
from firmware.app import App
""" + H.FAKE_HAL + r"""
class VHal(Hal):
    # the shared stand-in HAL (fwharness.FAKE_HAL) with a supply reading
    def __init__(self):
        Hal.__init__(self)
        self.mv = 12000
    def read_supply_mv(self):
        return self.mv
h0, h1 = VHal(), VHal()
cfg = {'watchdog_ms': 0, 'vsup_nom_mv': 12000, 'vsup_min_mv': 9000}
a0 = App(h0, config=cfg)
a1 = App(h1, config=cfg)
s1 = F.SupplyV(a1)
n = 0
for i in range(3000 // DIV):
    mv = pick((12000, 11990, 8000, 9000, 8999, 0, 30000)) if rnd(20) == 0 else 9000 + rnd(6000)
    h0.mv = h1.mv = mv
    st = rnd(4)
    if a0._supply(st) != s1.update(st):
        bad['supply'] = bad.get('supply', 0) + 1
    for k in ('_vsup_acc', 'vsup_mv'):
        if getattr(a0, k) != getattr(a1, k):
            bad['supply'] = bad.get('supply', 0) + 1
    if a0.motor.vscale != a1.motor.vscale:
        bad['supply'] = bad.get('supply', 0) + 1
    n += 1
print('supply_n', n)
print('bad', sum(bad.values()), bad)
"""

APP = H.FAKE_HAL + H.APP_STEPS_LOCKED + r"""
from firmware.app import App
from firmware import fasttick as F
hal = Hal()
app = App(hal, config={'watchdog_ms': 0, 'emitter': 'viper'})
print('classes', int(isinstance(app.sensors, F.SensorsV)) + int(isinstance(app.sup, F.SupervisorV))
      + int(isinstance(app.motor, F.MotorV)) + int(isinstance(app.timing, F.TimingV)))
print('alloc_free', steps_locked(hal, app, 2000))
print('state', app.sup.state)
"""


def _check(out: str, div: int = 1) -> None:
    # div: the script's iterations were divided by it (DIV; 1 on the host's interpreters)
    lines = dict(line.split(" ", 1) for line in out.splitlines() if line.strip() and not line.startswith("diff"))
    assert int(lines["consts_bad"]) == 0
    assert int(lines["sensors_n"]) == 6000 // div and int(lines["sup_n"]) == 20000 // div
    assert int(lines["motor_n"]) == 8000 // div and int(lines["timing_n"]) == 6000 // div
    assert int(lines["pacer_n"]) == 4200 // div
    assert int(lines["consts_bad2"]) == 0 and int(lines["supply_n"]) == 3000 // div
    assert int(lines["bad"].split()[0]) == 0, out


# the script's iterations divided on the emulated board (it runs at ~0.15x real time)
METHODS_DIV = {"rp2040": 10}


@pytest.mark.interps("cpython", "unix", "rp2040")
def test_viper_methods_equal_the_plain_ones(interp: H.Interp) -> None:
    # the viper build on the unix port and the board's armv6m .mpy, the CPython fallback
    div = METHODS_DIV.get(interp.name, 1)
    _check(interp.run(SCRIPT.replace("DIV = 1 ", f"DIV = {div} ", 1), timeout=240), div)


def test_app_with_viper_builds_them_and_steps_allocation_free() -> None:
    out = dict(line.split() for line in run_unix(APP, timeout=120).splitlines() if line.strip())
    assert out["classes"] == "4"
    assert out["alloc_free"] == "1"
    assert out["state"] == "2"


# Whole apps: App.step (bytecode) against StepV.step (App(config={"emitter": "viper"})), tick by
# tick on the same readings and commands: arming, balancing and its start, catch mode, faults
# of every kind the step raises (tilt, rail, jump, track, stall, watchdog, e-stop, undervoltage,
# open wiper, pending deadline), clear, excitation, the driver enable, the motor sign, the
# clock wrap; every returned duty, what each HAL saw and every attribute the step touches
APP_EQ = H.FAKE_HAL + r"""
DIV = 1  # ticks / DIV (the emulated board: tests/test_rp2040_fast_equal.py)
from firmware.app import App
from firmware import msgtable as T
seed = [2026]
def rnd(n):
    seed[0] = (seed[0] * 1103515245 + 12345) & 0x7FFFFFFF
    return (seed[0] >> 8) % n

class Hal2(Hal):
    def __init__(s):
        Hal.__init__(s)
        s.stop = False
        s.mv = 12000
        s.adc_open = False
        s.frames = 0
        s.n_sensor = 0
        s.en = []
    def estop(s):
        return s.stop
    def read_supply_mv(s):
        return s.mv
    def set_enable(s, on):
        s.en.append(on)

APPA = ('duty', 'tick', 'uptime_ms', '_us_frac', 'step_us', 'epoch', '_st', '_ext', '_en', '_frames', '_vsup_acc',
        'vsup_mv')
SUPA = ('state', 'faults', 'last', 'wd_count', 'stall_count')
SENA = ('counts', 'pos', 'yx', 'yp', 'delta', 'rail', 'jump', 'last', 'primed')
TMA = ('step_min', 'step_max', 'overruns', 'steps', 'mean_us', 'period_max', 'jitter_max', 'last_us')
CTA = ('u', 'vh', 'catching', 'n_catch')
bad = [0]
def cmp(name, a, b, attrs):
    for k in attrs:
        x, y = getattr(a, k), getattr(b, k)
        if x != y:
            bad[0] += 1
            if bad[0] < 6:
                print('diff', name, k, x, y)

ticks = 0
catches = 0
flags = 0
nbal = 0
nexc = 0
seen = set()
for full in (0, 1):
    H0 = Hal2() if full else Hal()
    H1 = Hal2() if full else Hal()
    cfg = {'watchdog_ms': 100, 'stall_ms': 20, 'stall_duty': 400, 'epoch': 7}
    if full:
        cfg['vsup_nom_mv'] = 12000
        cfg['vsup_min_mv'] = 9000
    a = App(H0, config=dict(cfg))
    cfg['emitter'] = 'viper'
    b = App(H1, config=cfg)
    H0.t = H1.t = 0x3FFFFFFF - 200000  # the clock wraps during the run
    adc = a.sensors.pot_offset
    enc = 0
    hold = 0
    still = 0
    for k in range(6000 // DIV):
        r = rnd(400)
        # commands between ticks, the same on both
        if r < 6:
            a.cmd_arm(); b.cmd_arm()
        elif r == 6:
            a.cmd_disarm(); b.cmd_disarm()
        elif r < 10:
            a.cmd_clear_faults(); b.cmd_clear_faults()
            adc = a.sensors.pot_offset + rnd(21) - 10
        elif r == 10:
            um = (rnd(401) - 200) * 1000
            a.cmd_set_reference(um); b.cmd_set_reference(um)
        elif r == 11:
            m, amp, dv = rnd(3), 200 + rnd(800), 1 + rnd(4)
            a.cmd_excite(m, amp, dv); b.cmd_excite(m, amp, dv)
        elif r == 12:
            v = 1 - 2 * rnd(2)
            a.param_set(T.P_MOTOR_SIGN, v); b.param_set(T.P_MOTOR_SIGN, v)
        elif r == 13:
            a._ext |= 256; b._ext |= 256  # a deadline the paced loop found
        elif r == 14:
            v = rnd(5) != 0  # the paced loop found its period (not yet)
            a.sup.timing_ok = v; b.sup.timing_ok = v
        elif r == 15 and full:
            H0.stop = H1.stop = rnd(8) == 0
        elif r == 16 and full:
            H0.mv = H1.mv = 8000 + rnd(5000)
        elif r == 17 and full:
            H0.adc_open = H1.adc_open = rnd(8) == 0
        elif r == 18 and full:
            H0.n_sensor += 1; H1.n_sensor += 1
        elif r < 40:
            a.feed_watchdog(); b.feed_watchdog()
        elif r < 48:
            a.cmd_clear_faults(); b.cmd_clear_faults()
        # readings: near upright, now and then a large tilt (catch mode), a rail, a jump
        q = rnd(400)
        if hold > 0:
            hold -= 1
            q = 99
        elif q == 0 or q == 5:
            # a large tilt held for a while: 40-110 % of the tilt limit (catch mode above
            # 0.2 rad, F_TILT beyond the limit), the cart held still half the time (F_STALL)
            adc = a.sensors.pot_offset + (rnd(2) * 2 - 1) * (a.sup.tilt_counts * (40 + rnd(71)) // 100)
            hold = 10 + rnd(30)
            still = rnd(2)
        elif q == 4:
            hold = 10 + rnd(30)  # a quiet pendulum
            still = 0
        elif q == 1:
            adc = (0, 4095, 5000, -3)[rnd(4)]
        elif q == 2:
            adc = a.sensors.pot_offset + rnd(41) - 20
        elif q != 99:
            adc += rnd(7) - 3
            if adc > a.sensors.pot_offset:
                adc -= rnd(3)
            else:
                adc += rnd(3)
        if q == 3:
            enc = (enc + 9000) & 0xFFFF
        elif q < 40 or (q == 99 and still):
            pass  # the cart does not move (stall check)
        else:
            enc = (enc + rnd(41) - 20) & 0xFFFF
        H0.adc = H1.adc = adc
        H0.enc = H1.enc = enc
        H0.inc = H1.inc = (250, 250, 250, 700, 1200, 30000)[rnd(6)]
        da = a.step()
        db = b.step()
        ticks += 1
        seen.add(a.sup.state)
        flags |= a.sup.last
        nbal += a.sup.state == 2
        nexc += a.exc.on
        if da != db or H0.duty != H1.duty or H0.n_set != H1.n_set:
            bad[0] += 1
            if bad[0] < 6:
                print('diff duty', k, da, db, H0.duty, H1.duty)
        if full and H0.en != H1.en:
            bad[0] += 1
        cmp('app', a, b, APPA)
        cmp('sup', a.sup, b.sup, SUPA)
        cmp('sensors', a.sensors, b.sensors, SENA)
        cmp('timing', a.timing, b.timing, TMA)
        cmp('ctrl', a.ctrl, b.ctrl, CTA)
        if list(a.ctrl.xf) != list(b.ctrl.xf) or a.exc.on != b.exc.on or a.motor.vscale != b.motor.vscale:
            bad[0] += 1
    catches += a.ctrl.n_catch
    print('faults', a.sup.faults | 0)
print('app_ticks', ticks)
print('states', len(seen))
print('catches', catches)
print('flags', flags)
print('balancing', nbal)
print('excited', nexc)
print('app_bad', bad[0])
"""


def _check_app(out: str) -> None:
    lines = dict(line.split(" ", 1) for line in out.splitlines() if line.strip() and not line.startswith(("diff", "faults")))
    assert int(lines["app_ticks"]) == 12000
    assert int(lines["states"]) == 4  # disarmed, armed, balancing and fault all reached
    assert int(lines["catches"]) > 0  # the catch row was switched in
    # tilt, watchdog, rail, jump, track, stall, deadline, e-stop, open wiper raised
    need = 1 | 2 | 4 | 8 | 16 | 64 | 256 | 512 | 8192
    assert int(lines["flags"]) & need == need, out
    assert int(lines["balancing"]) > 1000 and int(lines["excited"]) > 0, out
    assert int(lines["app_bad"]) == 0, out


@pytest.mark.interps("cpython", "unix")  # the emulated board's fewer ticks: test_rp2040_fast_equal.py
def test_viper_step_equals_app_step(interp: H.Interp) -> None:
    _check_app(interp.run(APP_EQ, timeout=240))
