"""Simulated identification logs, for validating ``upright identify`` (issue 15 item 4).

The logs have the columns and the quantisation of a log ``upright board excite`` records
(``host.operate.record.COLUMNS`` plus ``excite``; x and phi in the telemetry's 1e-4
steps, as the firmware sends the sensors while an excitation runs; the integer duty):

- :func:`balancing_log`: the nonlinear plant (:class:`sim.plantsim.PlantSim`, delayed and
  quantised sensors, optional noise) closed around the float discrete controller of the
  design, with the firmware's own PRBS (:class:`firmware.excite.Excite`, mode 1) added to
  the force and stored for the predictor as the firmware does;
- :func:`cart_log`: the cart alone (pendulum removed), driven open loop by the PRBS (mode 2:
  duty from the force without back-EMF compensation), then coasting with the driver off.

:func:`perturbed_plant` draws a plant from the issue's uncertainty set.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np

from firmware.excite import Excite
from host.design.discrete import controller_ss
from sim import motor as smotor
from sim import sensors as ssens
from sim.params import RobotParams
from sim.plantsim import PlantSim
from sim.scenario import Scenario
from sim.sensors import NoiseModel

__all__ = ["balancing_log", "cart_log", "perturbed_plant", "write_log", "known_params", "UNCERTAINTY"]

UNCERTAINTY = {"I": (0.5, 1.2), "mass": (0.8, 1.2), "b": (0.5, 2.0), "delay": (0.0, 0.02), "kt": (0.9, 1.1),
               "pot_offset": (-40, 40)}
"""The issue's uncertainty set (factors; delay in s; pot offset error in counts)."""

COLUMNS = ("t", "seq", "x", "xdot", "phi", "phidot", "ref", "force", "duty", "step_us", "state", "faults")
"""host.operate.record.COLUMNS (a higher layer: tests/test_identify.py checks the two agree)."""
TEL_X = 1e-4  # telemetry steps of x (m) and phi (rad): msgtable TELEM_STATE
TEL_PHI = 1e-4


def _prbs_signs(n: int, div: int) -> np.ndarray:
    # the firmware's sequence (firmware/excite.py), +-1 per tick
    ex = Excite()
    ex.start(1, 1000, div, 0, 4)
    ex.amp = 1
    return np.array([ex.next() for _ in range(n)], dtype=float)


def perturbed_plant(design: RobotParams, rng: np.random.Generator | None = None, **factors: float) -> RobotParams:
    """A plant from :data:`UNCERTAINTY`: given factors, the rest drawn uniformly.

    Keys: ``I`` (x the design's pivot inertia term), ``M``, ``m`` (mass factors), ``b``,
    ``kt`` (factors), ``delay`` (s, rounded to whole ticks), ``pot_offset`` (counts added).
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    U = UNCERTAINTY

    def pick(k: str, lo: float, hi: float) -> float:
        return float(factors[k]) if k in factors else float(rng.uniform(lo, hi))

    fI = pick("I", *U["I"])
    fM, fm = pick("M", *U["mass"]), pick("m", *U["mass"])
    fb, fk = pick("b", *U["b"]), pick("kt", *U["kt"])
    d = pick("delay", *U["delay"])
    dp = pick("pot_offset", *U["pot_offset"])
    v = design.values
    p = design.replace(**{"cart.M": v["cart.M"] * fM, "pendulum.m_cam": v["pendulum.m_cam"] * fm,
                          "pendulum.m_shaft": v["pendulum.m_shaft"] * fm})
    rate = design.rate
    return p.replace(**{"pendulum.I": p.I * fI, "cart.b": v["cart.b"] * fb, "motor.kt": v["motor.kt"] * fk,
                        "sensors.delay": round(d * rate) / rate,
                        "sensors.pot_offset": int(round(v["sensors.pot_offset"] + dp))})


def known_params(design: RobotParams, plant: RobotParams) -> RobotParams:
    """What a user knows of ``plant``: the design's file with the weighed masses."""
    v = plant.values
    return design.replace(**{"cart.M": v["cart.M"], "pendulum.m_cam": v["pendulum.m_cam"],
                             "pendulum.m_shaft": v["pendulum.m_shaft"]})


def _rows(x: np.ndarray, phi: np.ndarray, duty: np.ndarray, force: np.ndarray, state: np.ndarray,
          mode: int, rate: float) -> dict[str, np.ndarray]:
    n = len(x)
    z = np.zeros(n)
    return {"t": np.arange(n) / rate, "seq": (np.arange(n) * 2) % 256, "x": np.round(x / TEL_X) * TEL_X,
            "xdot": z, "phi": np.round(phi / TEL_PHI) * TEL_PHI, "phidot": z, "ref": z,
            "force": np.round(force, 2), "duty": duty.astype(int), "step_us": z + 300, "state": state.astype(int),
            "faults": z.astype(int), "excite": np.full(n, mode)}


def balancing_log(plant: RobotParams, design: RobotParams, *, seconds: float = 20.0, amp: float = 0.6,
                  div: int = 8, phi_noise: float = 5e-4, seed: int = 1) -> dict[str, np.ndarray]:
    """A balancing run with the firmware's PRBS of ``amp`` N added to the force (mode 1).

    ``phi_noise``: white noise on the tilt (rad rms per sample) on top of the quantisation.
    """
    Ts = 1.0 / design.rate
    noise = NoiseModel(kind="white", power=phi_noise**2 * Ts, channels=("phi",)) if phi_noise > 0 else NoiseModel()
    sc = Scenario(name="identify", duration=seconds, seed=seed, noise=noise)
    sim = PlantSim(plant, sc, seed=seed)
    ctrl = controller_ss(design)
    Ac, Bc, Cc, Dc = (np.asarray(m_, dtype=float) for m_ in (ctrl.Ac, ctrl.Bc, ctrl.Cc, ctrl.Dc))
    Bu = np.asarray(ctrl.Bu, dtype=float)[:, 0]
    umax = float(ctrl.u_max)
    from sim.plantsim import _linear_rows

    Ez, Ev = _linear_rows(ctrl)
    cpm, cpr, off = float(ssens.enc_counts_per_m(design)), float(ssens.adc_counts_per_rad(design)), design.pot_offset
    n = sim.n_ticks
    ex = _prbs_signs(n, div) * min(amp, umax / 2)
    z = np.zeros(Ac.shape[0])
    total, last = 0, sim.read()[1]
    xs, ps, du, fo = (np.zeros(n) for _ in range(4))
    for k in range(n):
        adc, enc = sim.read()
        dd = (enc - last) % ssens.ENC_MODULUS
        total += dd - ssens.ENC_MODULUS if dd >= ssens.ENC_MODULUS // 2 else dd
        last = enc
        xm, phm = total / cpm, (adc - off) / cpr
        v = np.array([xm, phm, 0.0])
        u = float(Cc[0] @ z + Dc[0] @ v)
        us = min(max(u + ex[k], -umax), umax)
        xd_est = float(Ez[1] @ z + Ev[1] @ v)
        duty = int(smotor.duty_from_force(us, xd_est, design))
        z = Ac @ z + Bc @ v + Bu * us
        sim.step(duty)
        xs[k], ps[k], du[k], fo[k] = xm, phm, duty, us
    return _rows(xs, ps, du, fo, np.full(n, 2), 1, design.rate)


def cart_log(plant: RobotParams, design: RobotParams, *, seconds: float = 8.0, coast_s: float = 4.0,
             amp: float = 1.2, div: int = 4, seed: int = 2, latency: float = 0.0, brake: float = 0.0,
             substeps: int = 16) -> dict[str, np.ndarray]:
    """A cart-only run: PRBS of ``amp`` N open loop (mode 2), then ``coast_s`` with the driver off.

    The cart alone (mass ``M``): ``M xdd = F - b xd``, ``F = a duty - c_emf xd`` while driven,
    ``F = 0`` while coasting; the encoder counts delayed by the plant's delay, then the
    telemetry's 1e-4 m steps.  ``latency`` (ticks, 0..1): each tick's duty is applied that
    much after the tick's reading, as on a board (its computation); ``brake`` (ticks): the
    bridge stays enabled at duty 0 that long after the disarm's duty (the enable's delay).
    Without them each tick is exact (the duty held); with them ``substeps`` exact sub-steps.
    A plant with plant realism (Coulomb and static friction, gear play with the encoder on the
    motor shaft, the bridge's deadband and minimum duty) runs :class:`sim.plantsim.PlantSim`'s
    own integrator with the pendulum's mass off, ``substeps`` sub-steps a tick.
    """
    rate = design.rate
    Ts = 1.0 / rate
    nd, nc = int(round(seconds * rate)), int(round(coast_s * rate))
    n = nd + nc
    sg = _prbs_signs(nd, div)
    duty = np.zeros(n)
    duty[:nd] = smotor.duty_from_force(sg * amp, 0.0, design)
    c = smotor.motor_constants(plant)
    fpa = c["n_motors"] * c["gear"] * c["kt"] / c["r_wheel"]
    a_d = fpa * c["V_supply"] / (smotor.DUTY_MAX * c["R"])
    ce = fpa * c["kt"] * c["gear"] / (c["r_wheel"] * c["R"])
    M, b = plant.M, plant.b
    x = np.zeros(n + 1)
    v = 0.0
    S = int(substeps) if (latency or brake) else 1
    h = Ts / S
    t_off = nd + latency + brake  # the enable's edge (ticks)
    if not plant.ideal:
        # plant realism: the simulators' own cart (PlantSim's integrator, pendulum off)
        x = _cart_real_positions(plant, duty, nd, latency, brake, int(substeps))
    for k in range(n if plant.ideal else 0):
        xk = x[k]
        for j in range(S):
            t = k + j / S
            u = duty[k] if t >= k + latency else (duty[k - 1] if k else 0.0)
            on = t < t_off
            lam = (b + (ce if on else 0.0)) / M
            F = a_d * u / M if on else 0.0
            e = math.exp(-lam * h)
            vinf = F / lam
            # exact: v -> vinf + (v - vinf) e; x += vinf h + (v - vinf)(1 - e)/lam
            xk += vinf * h + (v - vinf) * (1.0 - e) / lam
            v = vinf + (v - vinf) * e
        x[k + 1] = xk
    d = int(round(plant.delay * rate))
    xd = np.concatenate([np.zeros(d), x[:n - d]]) if d else x[:n]
    enc = np.rint(xd * float(ssens.enc_counts_per_m(plant)))
    xm = enc / float(ssens.enc_counts_per_m(design))
    state = np.where(np.arange(n) < nd, 2, 0)
    rng = np.random.default_rng(seed)
    phi = np.round(rng.normal(0.0, 2e-4, n), 4)  # the locked pendulum: the pot's noise only
    force = np.zeros(n)
    force[:nd] = sg * amp
    return _rows(xm, phi, duty, force, state, 2, rate)


class _CartAlone(PlantSim):
    # the cart alone with plant realism, as host.hil.virtual_robot.RobotPlant runs it with the
    # pendulum off: PlantSim's integrator with the pendulum's mass taken off (m L = 0: the
    # cart's row is M xdd = F - b xd - Coulomb, the pendulum's 0), one sub-step per plant tick

    def __init__(self, plant: RobotParams, S: int, seconds: float) -> None:
        p = plant.replace(rate=plant.rate * S)
        super().__init__(p, Scenario(name="cart_log", duration=seconds), ground_stop=False)
        self._m = self._mL = 0.0
        self._ce_on = self._c_emf

    def sub(self, duty: float, on: bool) -> None:
        # one sub-step: the bridge enabled (duty, back-EMF braking) or off (no current)
        self._c_emf = self._ce_on if on else 0.0
        d = min(max(int(duty), -smotor.DUTY_MAX), smotor.DUTY_MAX) if on else 0
        self._integrate(d, self.t)
        self._x[2] = self._x[3] = 0.0
        self.tick += 1

    @property
    def encoder_x(self) -> float:
        # the encoder is on the motor shaft: the cart plus the motor side of the gear play
        return self._x[0] + self._delta


def _cart_real_positions(plant: RobotParams, duty: np.ndarray, nd: int, latency: float, brake: float,
                         S: int) -> np.ndarray:
    # encoder-side positions at each tick of a cart-only run on a plant with realism: S sub-steps
    # a tick, each tick's duty from ``latency`` ticks after its reading, the bridge enabled until
    # ``nd + latency + brake`` ticks (cart_log's timing)
    n = len(duty)
    sim = _CartAlone(plant, S, (n + 1) / plant.rate)
    x = np.zeros(n + 1)
    t_off = nd + latency + brake
    for k in range(n):
        for j in range(S):
            t = k + j / S
            u = duty[k] if t >= k + latency else (duty[k - 1] if k else 0.0)
            sim.sub(u, t < t_off)
        x[k + 1] = sim.encoder_x
    return x


def write_log(log: dict[str, Any], path: str | Path) -> Path:
    """Write a simulated log as ``upright board excite`` would (CSV, same header)."""
    p = Path(path)
    cols = (*COLUMNS, "excite")
    with open(p, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for i in range(len(log["x"])):
            w.writerow([_cell(log[c][i]) for c in cols])
    return p


def _cell(v: Any) -> str:
    f = float(v)
    return str(int(f)) if f.is_integer() else f"{f:.6g}"


# the hooks of host.boards.fwharness.PipedApp's loop: EXCITE(mode, amp_mn, div) from a line's
# words 3-5 (its result r, -1 without); the reply is the duty, the state, the telemetry the board
# would send (x, phi, force), the excitation's mode and r
_EXCITE_HOOKS = """
from array import array
tel = array('i', [0] * 8)
def start(app):
    pass
def command(app, w):
    if len(w) > 2:
        return app.cmd_excite(int(w[2]), int(w[3]), int(w[4]))
    return -1
def reply(hal, app, r):
    app.fill_telemetry(tel)
    return '%d %d %d %d %d %d %d\\n' % (hal.duty, app.sup.state, tel[0], tel[2], tel[5], app.exc.mode, r)
"""


def firmware_balancing_log(plant: RobotParams, *, seconds: float = 30.0, amp_mn: int = 600, div: int = 8,
                           phi_noise: float = 5e-4, seed: int = 1, start_s: float = 0.5) -> dict[str, np.ndarray]:
    """A balancing run with the firmware in the loop: the real App (shipped gain table) under
    the MicroPython unix port, stepped tick by tick against :class:`PlantSim`; after
    ``start_s`` the host sends EXCITE(1, amp_mn, div) and the log takes the telemetry the
    board would send (x, phi: the sensors in 1e-4 steps; force: 0.01 N), as ``upright board
    excite`` records it.

    Raises
    ------
    RuntimeError
        The interpreter stopped, the board refused EXCITE, or it stopped balancing.
    """
    from host.boards.fwharness import PipedApp

    rate = plant.rate
    Ts = 1.0 / rate
    noise = NoiseModel(kind="white", power=phi_noise**2 * Ts, channels=("phi",)) if phi_noise > 0 else NoiseModel()
    sim = PlantSim(plant, Scenario(name="identify_fw", duration=seconds + start_s, seed=seed, noise=noise), seed=seed)
    adc0, enc0 = sim.read()
    cfg = {"watchdog_ms": 0, "stall_ms": 0, "arm_tilt_mrad": 150}
    n0 = int(round(start_s * rate))
    n = sim.n_ticks
    rows = np.zeros((n - n0, 5))
    with PipedApp(_EXCITE_HOOKS, cfg, adc0, enc0) as fw:
        for k in range(n):
            adc, enc = sim.read()
            words = (1, amp_mn, div) if k == n0 else ()
            duty, state, tx, tp, tf, mode, r = fw.tick(adc, enc, *words)
            if k == n0 and r != 0:
                raise RuntimeError(f"EXCITE refused by the firmware (reason {r})")
            if k >= n0:
                if state != 2:
                    raise RuntimeError(f"the firmware stopped balancing at tick {k} (state {state})")
                rows[k - n0] = (tx * 1e-4, tp * 1e-4, tf * 0.01, duty, mode)
            sim.step(duty)
    m = len(rows)
    return _rows(rows[:, 0], rows[:, 1], rows[:, 3], rows[:, 2], np.full(m, 2), 1, rate)
