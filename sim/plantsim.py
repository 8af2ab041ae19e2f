"""The plant side of a closed loop, one control tick at a time: shared by HIL and pure simulation.

:class:`PlantSim` holds the robot's true state and, each control tick, does what the physical
robot would do between two loop iterations of the board:

1. :meth:`PlantSim.read` -- the sensor values the board reads at this tick: ADC counts of the
   angle potentiometer and the 16-bit encoder counter, with the scenario's noise, quantised,
   and ``delay_steps`` ticks old (:class:`sim.sensors.SensorModel`).
2. :meth:`PlantSim.step` -- the board's answer, a PWM duty in ``[-32767, 32767]``, is held
   for one period ``Ts``; the DC motor model turns it into a force at the (changing) cart
   speed (:func:`sim.motor.force_from_duty`), the scenario adds its disturbance force, and
   the nonlinear plant (:func:`sim.plant.dynamics`) is integrated with classical RK4 in
   ``substeps`` steps of ``h = Ts/substeps`` (at least 1 kHz: 2 substeps of 1 ms at the
   default 500 Hz loop; over 1 s of a falling, driven pendulum RK4 at 1 ms agrees with 0.125 ms
   to ~1e-9 rad, see the tests).  A Dirac impulse of the scenario is applied as an
   instantaneous jump of the velocities at the start of the sub-step that contains it.

The HIL runner calls ``read()`` -> sends the frame -> gets the duty -> ``step(duty)``;
:func:`run_scenario_float` does the same with the float reference controller
(``host.design.discrete.DiscreteController``) in place of the board, so both use exactly this code.
Every tick is logged; :meth:`PlantSim.result` returns the log as arrays (:data:`LOG_COLUMNS`),
the input of :mod:`sim.metrics` and :mod:`sim.plots`.

Plant realism (the robot file's ``cart.coulomb``, ``cart.stiction``, ``motor.backlash``,
``motor.deadband``, ``motor.duty_min``, ``sensors.pot_inl``; docs/parameters.md, "Plant
realism"): off on the ideal robot (the defaults), whose ticks run the plain code below; with any
of them on, :meth:`PlantSim._integrate_real` decides the gear's contact and stuck/sliding at each
sub-step's start -- a contact within the sub-step located in it (:meth:`PlantSim._contact_share`),
a sliding cart that stops and is pushed the other way at once sliding on
(:meth:`PlantSim._stop`) -- (the scheme of :mod:`sim.batch`, which it agrees with to rounding), the encoder
reads the motor side of the gear play and the ADC the pot's nonlinearity.  :attr:`PlantSim.stuck`
and :attr:`PlantSim.gear_play` show the extra state.

For speed (the lockstep HIL budget is a fraction of a millisecond per tick) the per-tick
integration uses scalar ``math`` versions of the plant and motor equations; a test checks
them against :func:`sim.plant.dynamics` and :func:`sim.motor.force_from_duty`.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from . import motor, sensors
from .params import RobotParams
from .plant import accelerations, impulse_jump, pivot_fixed_phiddot
from .scenario import Scenario

__all__ = ["LOG_COLUMNS", "PlantSim", "run_scenario_float", "write_csv", "read_csv"]

_HALF_PI = 0.5 * math.pi

LOG_COLUMNS: dict[str, str] = {
    "t": "s, time of the tick",
    "x": "m, cart position at the tick",
    "xdot": "m/s, cart velocity",
    "phi": "rad, pendulum tilt from upright",
    "phidot": "rad/s, tilt rate",
    "x_ref": "m, cart position reference",
    "adc": "count, ADC reading the board got at this tick (delayed, noisy)",
    "enc": "count, 16-bit encoder counter the board got at this tick (delayed)",
    "duty": "PWM duty applied during the tick (-32767..32767)",
    "force": "N, motor force at the start of the tick",
    "f_dist": "N, finite disturbance force at the start of the tick",
    "xddot": "m/s^2, cart acceleration at the start of the tick (motor + disturbance)",
    "u_cmd": "N, controller force command before saturation (NaN if unknown)",
    "u_sat": "N, controller force command after saturation (NaN if unknown)",
}
"""Columns of a run log (one row per control tick) with their units."""



def _rk4(acc: Callable[[float, float, float, float], tuple[float, float]], x: float, xd: float, ph: float,
         phd: float, t: float, h: float) -> tuple[float, float, float, float]:
    # one classical RK4 step of [x, xd, ph, phd] on scalars; acc(xd, ph, phd, t) -> (xdd, phdd)
    h2, h6 = 0.5 * h, h / 6.0
    a1, b1 = acc(xd, ph, phd, t)
    v2, w2 = xd + h2 * a1, phd + h2 * b1
    a2, b2 = acc(v2, ph + h2 * phd, w2, t + h2)
    v3, w3 = xd + h2 * a2, phd + h2 * b2
    a3, b3 = acc(v3, ph + h2 * w2, w3, t + h2)
    v4, w4 = xd + h * a3, phd + h * b3
    a4, b4 = acc(v4, ph + h * w3, w4, t + h)
    return (x + h6 * (xd + 2.0 * v2 + 2.0 * v3 + v4), xd + h6 * (a1 + 2.0 * a2 + 2.0 * a3 + a4),
            ph + h6 * (phd + 2.0 * w2 + 2.0 * w3 + w4), phd + h6 * (b1 + 2.0 * b2 + 2.0 * b3 + b4))

class PlantSim:
    """The simulated robot, advanced one control tick at a time.

    Parameters
    ----------
    params : RobotParams
        Robot parameters (the scenario's ``[params]`` overrides and delay are applied).
    scenario : Scenario
        Initial state, disturbances, reference, noise, delay, seed.
    x0 : sequence of 4 float, optional
        Initial state overriding the scenario's.
    seed : int, optional
        Noise seed overriding the scenario's.
    substep_rate : float
        Minimum integration rate (Hz); at least 1000.
    ground_stop : bool
        A pendulum that falls to horizontal (``|phi| = pi/2``) lies there: it stops
        (``phidot = 0``, an inelastic hit) and stays until the cart's motion lifts it again;
        ``fallen`` becomes true.  ``False`` lets it swing through, as the bare equations do.

    Attributes
    ----------
    params : RobotParams
        The parameters actually simulated.
    Ts : float
        Control period (s).
    substeps : int
        RK4 steps per control tick.
    tick : int
        Index of the current tick (the next ``step`` applies to it).
    state : ndarray
        True state ``[x, xdot, phi, phidot]`` at the current tick.
    """

    def __init__(
        self,
        params: RobotParams,
        scenario: Scenario,
        *,
        x0: Sequence[float] | None = None,
        seed: int | None = None,
        substep_rate: float = 1000.0,
        ground_stop: bool = True,
    ) -> None:
        if not substep_rate >= 1000.0:
            raise ValueError(f"substep_rate must be >= 1000 Hz, got {substep_rate!r}")
        self.params = p = scenario.apply(params)
        self.scenario = scenario
        self.Ts = 1.0 / p.rate
        self.substeps = max(1, math.ceil(substep_rate * self.Ts - 1e-9))
        self.h = self.Ts / self.substeps
        self.n_ticks = int(round(scenario.duration * p.rate))
        self.tick = 0
        x = [float(v) for v in (scenario.x0 if x0 is None else x0)]
        if len(x) != 4 or not all(math.isfinite(v) for v in x):
            raise ValueError(f"x0 must be 4 finite numbers, got {x0!r}")
        self._x = x
        self.ground_stop = bool(ground_stop)
        self.fallen = False
        # physical constants for the scalar right-hand side
        ph = p.physical
        self._M, self._m, self._L, self._I, self._b, self._g = ph["M"], ph["m"], ph["L"], ph["I"], ph["b"], ph["g"]
        self._J = self._I + self._m * self._L**2
        self._mL = self._m * self._L
        # motor: F = a_duty * duty - c_emf * xdot  (duty clipped to the supply)
        fpa = p.n_motors * p.gear * p.kt / p.r_wheel
        self._a_duty = fpa * p.V_supply / (motor.DUTY_MAX * p.R)
        self._c_emf = fpa * p.kt * p.gear / (p.r_wheel * p.R)
        # plant realism (docs/parameters.md, "Plant realism"): off on the ideal robot, whose
        # code path is the plain one below
        r = p.realism
        self._real = not p.ideal
        self._fc = r["coulomb"]
        self._fs = max(r["stiction"], r["coulomb"])
        self._fric = self._fs > 0.0
        self._half_play = 0.5 * r["backlash"]
        self._db, self._dmin = r["deadband"] * motor.DUTY_MAX, r["duty_min"] * motor.DUTY_MAX
        self._delta = 0.0  # motor side minus wheel side of the gear play (m of cart travel)
        self._stuck = self._fric and x[1] == 0.0  # a cart at rest is held by static friction
        self._dir = 1.0 if x[1] >= 0.0 else -1.0  # direction of sliding (Coulomb friction opposes it)
        self._dist = self._disturbance_fn()
        self._has_dist = any(not f.is_dirac for f in scenario.forces)
        self._diracs = sorted((t, imp) for t, imp in scenario.dirac_impulses(0.0, math.inf))
        self.sensor_model = sensors.SensorModel(
            p, noise=scenario.noise, rng=scenario.seed if seed is None else seed
        )
        self.sensor_model.reset(x[0], x[2])
        self._reading = self._measure()
        self._log: dict[str, list[float]] = {k: [] for k in LOG_COLUMNS}

    # ------------------------------------------------------------------ plant
    def _disturbance_fn(self) -> Callable[[float], float]:
        finite = [f for f in self.scenario.forces if not f.is_dirac]
        spans = []
        for f in finite:
            level = f.amplitude if f.kind == "push" else f.impulse / f.width
            spans.append((f.start, f.end, level))

        def dist(t: float) -> float:
            s = 0.0
            for a, b, lv in spans:
                if a <= t < b:
                    s += lv
            return s

        return dist

    def _duty_eff(self, d: float) -> float:
        # the H-bridge's minimum duty and deadband (sim.motor.bridge_fraction, in duty counts)
        a = abs(d)
        if a < self._dmin:
            a = 0.0
        a = a - self._db
        return math.copysign(a if a > 0.0 else 0.0, d)

    def _engagement(self) -> int:
        # gear play: +1 motor against the wheel's forward flank, -1 the backward one, 0 free, 2 no play
        hp = self._half_play
        if hp == 0.0:
            return 2
        return 1 if self._delta >= hp else (-1 if self._delta <= -hp else 0)

    @staticmethod
    def _gate(F: float, eng: int) -> float:
        # the motor force the gear passes: all of it without play, only a push into the flank in contact
        if eng == 2:
            return F
        if eng == 1:
            return F if F > 0.0 else 0.0
        if eng == -1:
            return F if F < 0.0 else 0.0
        return 0.0

    @staticmethod
    def _contact_share(eng: int, delta: float, hp: float, rel: float, h: float) -> float:
        # the motor side free in the gear play (eng 0) at delta, moving at rel against the wheel
        # side (its no-load speed fu / ce minus the cart's): the share of a sub-step h after it
        # touches a flank (0: it does not within h).  The contact is located in the sub-step (at the relative speed of
        # its start), not put off to the next: the force it passes from there is a jump, and a
        # contact decided only at sub-step starts comes up to a sub-step late, an error of
        # the order of h that made the cart with play converge only at 32 sub-steps a tick
        # (docs/parameters.md, "Plant realism")
        if eng != 0 or hp == 0.0:
            return 0.0
        if rel > 0.0:
            tc = (hp - delta) / rel
        elif rel < 0.0:
            tc = (-hp - delta) / rel
        else:
            return 0.0
        if tc >= h:
            return 0.0
        return 1.0 - tc / h if tc > 0.0 else 1.0

    @staticmethod
    def _stop(v_in: float, v: float, dr: float, f_rest: float, fc: float, fs: float, h: float,
              m: float) -> tuple[float, float, bool]:
        # a sliding cart (direction dr, speed v_in at the sub-step's start) whose speed reversed
        # within the sub-step (v): (speed, direction, stuck) at its end.  Held by static friction
        # (0, dr, True) unless the force on it at rest, f_rest, breaks it loose the other way at
        # once: then it slides on, the friction turned at the stop (located by the speed's
        # zero), not held for the rest of the sub-step -- that loses the drive's push over it,
        # an error of the order of h (docs/parameters.md, "Plant realism")
        if f_rest * dr < 0.0 and abs(f_rest) > fs:
            ts = h * v_in / (v_in - v) if v_in != v else h
            return v + 2.0 * fc * dr * (h - ts) / m, -dr, False
        return 0.0, dr, True

    def _drive_force(self, duty: float, xd: float) -> float:
        # the motor force on the cart at speed xd, through the bridge and the gear play
        if not self._real:
            return self._a_duty * duty - self._c_emf * xd
        return self._gate(self._a_duty * self._duty_eff(duty) - self._c_emf * xd, self._engagement())

    def _rhs(self, x: list[float], duty: float, t: float) -> tuple[float, float, float, float]:
        # sim.plant.dynamics for one state, with the motor force evaluated at this speed
        xd, phi, phid = x[1], x[2], x[3]
        mL, J = self._mL, self._J
        if self._real:
            if self._stuck:
                return 0.0, 0.0, phid, pivot_fixed_phiddot(math.sin(phi), mL * self._g, J)
            F = self._drive_force(duty, xd) + self._dist(t) - (self._fc * self._dir if self._fric else 0.0)
        else:
            F = self._a_duty * duty - self._c_emf * xd + self._dist(t)
        xdd, phidd = accelerations(F, xd, phid, math.sin(phi), math.cos(phi), self._M + self._m, mL, J, self._b,
                                   mL * self._g)
        return xd, xdd, phid, phidd

    def _apply_impulse(self, x: list[float], imp: float) -> list[float]:
        dxd, dphid = impulse_jump(x[2], imp, self._M + self._m, self._mL, self._J)
        return [x[0], x[1] + dxd, x[2], x[3] + dphid]

    def _integrate(self, duty: float, t0: float) -> None:
        # classical RK4 on scalars (_rk4), the equations sim.plant.accelerations
        if self._real:
            self._integrate_real(duty, t0)
            return
        x, xd, ph, phd = self._x
        h = self.h
        Mt, mL, J, b, g = self._M + self._m, self._mL, self._J, self._b, self._g
        mLg = mL * g
        fu = self._a_duty * duty
        ce = self._c_emf
        dist = self._dist if self._has_dist else None
        sin, cos = math.sin, math.cos

        def acc(v: float, p: float, w: float, t: float) -> tuple[float, float]:
            F = fu - ce * v + (dist(t) if dist is not None else 0.0)
            return accelerations(F, v, w, sin(p), cos(p), Mt, mL, J, b, mLg)

        for i in range(self.substeps):
            t = t0 + i * h
            while self._diracs and self._diracs[0][0] < t + h - 1e-12:
                x, xd, ph, phd = self._apply_impulse([x, xd, ph, phd], self._diracs.pop(0)[1])
            x, xd, ph, phd = _rk4(acc, x, xd, ph, phd, t, h)
            if self.ground_stop and abs(ph) >= _HALF_PI:
                ph, phd = self._on_ground(ph, phd)
        self._x = [x, xd, ph, phd]

    def _on_ground(self, ph: float, phd: float) -> tuple[float, float]:
        # lying on the ground: stopped there unless already rising again
        self.fallen = True
        ph = math.copysign(_HALF_PI, ph)
        return ph, (0.0 if phd * ph > 0 else phd)

    def _integrate_real(self, duty: float, t0: float) -> None:
        # RK4 with plant realism (docs/parameters.md, "Plant realism"), the same scheme as
        # sim.batch: the discontinuous parts are decided at each sub-step's start and held over it
        # (as the duty is over the tick) -- the gear's contact, sticking or sliding and the
        # sliding direction -- so that RK4 integrates a smooth right-hand side:
        #   stuck: the cart stands (x, xdot fixed), the pendulum swings about a fixed pivot; it
        #          breaks loose when the force static friction must hold exceeds the stiction;
        #   sliding: Coulomb friction -coulomb*dir; a sub-step that ends with the speed reversed
        #          (or zero) ends stuck at xdot = 0;
        #   gear play: the motor side moves at the motor's no-load speed while free (massless
        #          motor), delta += h*v0 - dx, clamped to the play; it pushes only while in contact.
        x, xd, ph, phd = self._x
        h = self.h
        Mt, mL, J, b, g = self._M + self._m, self._mL, self._J, self._b, self._g
        mLg = mL * g
        fu = self._a_duty * self._duty_eff(duty)
        ce = self._c_emf
        # the motor's no-load speed (m/s of cart travel): its force is ce * (v0 - xdot); with the
        # bridge off (ce 0: step(driven=0)) no current, no force, and the play does not move
        v0 = fu / ce if ce > 0.0 else math.nan
        hp = self._half_play
        fric, fc, fs = self._fric, self._fc, self._fs
        dist = self._dist if self._has_dist else None
        sin, cos = math.sin, math.cos
        gate = self._gate

        for i in range(self.substeps):
            t = t0 + i * h
            while self._diracs and self._diracs[0][0] < t + h - 1e-12:
                x, xd, ph, phd = self._apply_impulse([x, xd, ph, phd], self._diracs.pop(0)[1])
                if fric and xd != 0.0:
                    self._stuck, self._dir = False, (1.0 if xd > 0.0 else -1.0)
            eng = 2 if hp == 0.0 else (1 if self._delta >= hp else (-1 if self._delta <= -hp else 0))
            share = self._contact_share(eng, self._delta, hp, v0 - xd, h) if ce > 0.0 else 0.0
            if share > 0.0:
                eng = 1 if fu - ce * xd > 0.0 else -1
            if fric:
                if self._stuck:
                    # the force friction must hold for the cart to stay (xdd = 0, pivot fixed)
                    s, c = sin(ph), cos(ph)
                    g = gate(fu - ce * xd, eng)
                    fext = ((share * g if share > 0.0 else g) + (dist(t) if dist is not None else 0.0)
                            + mL * c * (mLg * s / J) - mL * phd * phd * s)
                    if abs(fext) > fs:
                        self._stuck, self._dir = False, (1.0 if fext > 0.0 else -1.0)
                elif xd != 0.0:
                    self._dir = 1.0 if xd > 0.0 else -1.0
            stuck = self._stuck
            ff = fc * self._dir if fric else 0.0

            def acc(v: float, p: float, w: float, tt: float) -> tuple[float, float]:
                s = sin(p)
                if stuck:
                    return 0.0, pivot_fixed_phiddot(s, mLg, J)
                g = gate(fu - ce * v, eng)
                F = (share * g if share > 0.0 else g) + (dist(tt) if dist is not None else 0.0) - ff
                return accelerations(F, v, w, s, cos(p), Mt, mL, J, b, mLg)

            x_old, xd_in = x, xd
            x, xd, ph, phd = _rk4(acc, x, xd, ph, phd, t, h)
            if fric and not stuck and xd * self._dir <= 0.0:
                # the sliding cart stopped during the sub-step: static friction holds it, unless
                # the force on it at rest breaks it loose the other way at once
                s, c = sin(ph), cos(ph)
                frest = (gate(fu, eng) + (dist(t + h) if dist is not None else 0.0)
                         + mL * c * (mLg * s / J) - mL * phd * phd * s)
                xd, self._dir, self._stuck = self._stop(xd_in, xd, self._dir, frest, fc, fs, h, Mt)
            if hp > 0.0 and ce > 0.0:
                d = self._delta + h * v0 - (x - x_old)
                self._delta = hp if d > hp else (-hp if d < -hp else d)
            if self.ground_stop and abs(ph) >= _HALF_PI:
                ph, phd = self._on_ground(ph, phd)
        self._x = [x, xd, ph, phd]

    def _measure(self) -> tuple[int, int]:
        # the encoder is on the motor shaft: it reads the motor side of the gear play
        xe = self._x[0] + self._delta if self._half_play else self._x[0]
        adc, enc = self.sensor_model.measure(xe, self._x[2])
        return int(adc), int(enc)

    # ------------------------------------------------------------------ public
    @property
    def t(self) -> float:
        """Time of the current tick (s)."""
        return self.tick * self.Ts

    @property
    def state(self) -> np.ndarray:
        """True state ``[x, xdot, phi, phidot]`` at the current tick (a copy)."""
        return np.array(self._x)

    @property
    def stuck(self) -> bool:
        """True while static friction holds the cart (plant realism; always False without friction)."""
        return self._stuck

    @property
    def gear_play(self) -> float:
        """Motor side minus wheel side of the gear play (m of cart travel, in +-backlash/2; 0 without it)."""
        return self._delta

    @property
    def done(self) -> bool:
        """True once the scenario's duration has been simulated."""
        return self.tick >= self.n_ticks

    def read(self) -> tuple[int, int]:
        """Sensor values the board reads at the current tick: ``(adc, enc)`` counts.

        Calling it again before :meth:`step` returns the same values.
        """
        return self._reading

    def peek(self, j: int) -> tuple[int, int]:
        """``(adc, enc)`` the board will read ``j`` ticks from now, ``1 <= j <= delay_steps``.

        Those readings were taken ``delay_steps - j`` ticks ago and wait in the delay line, so
        they do not depend on the duties still to come (a lockstep HIL host may send them
        ahead).  Raises ``ValueError`` outside that range.
        """
        adc, enc = self.sensor_model.peek(j)
        return int(adc), int(enc)

    def x_ref(self) -> float:
        """Cart position reference at the current tick (m)."""
        return self.scenario.reference.at(self.t)

    def step(self, duty: int, *, u_cmd: float = math.nan, u_sat: float = math.nan, driven: float = 1.0) -> None:
        """Apply ``duty`` for one control period and advance to the next tick.

        Parameters
        ----------
        duty : int
            PWM duty the board commanded for this tick; clipped to ``[-32767, 32767]`` by
            the bridge (the log keeps what was commanded).
        u_cmd, u_sat : float, optional
            The controller's force command before/after saturation, logged if known.
        driven : float
            Fraction of the tick the H-bridge was enabled (its EN pin high; default 1).  Enabled,
            it applies the duty and brakes through the back-EMF current at duty 0 (slow decay);
            disabled (EN low) its outputs are off: no current, the motor coasts.
        """
        if driven != 1.0:
            ce = self._c_emf
            self._c_emf = ce * min(1.0, max(0.0, float(driven)))
            try:
                PlantSim.step(self, duty if driven > 0.0 else 0, u_cmd=u_cmd, u_sat=u_sat)
            finally:
                self._c_emf = ce
            return
        d = min(max(int(duty), -motor.DUTY_MAX), motor.DUTY_MAX)
        t = self.t
        x = self._x
        fm = self._drive_force(d, x[1])
        fd = self._dist(t)
        log = self._log
        for name, v in (("t", t), ("x", x[0]), ("xdot", x[1]), ("phi", x[2]), ("phidot", x[3]),
                        ("x_ref", self.x_ref()), ("adc", self._reading[0]), ("enc", self._reading[1]),
                        ("duty", int(duty)), ("force", fm), ("f_dist", fd), ("xddot", self._rhs(x, d, t)[1]),
                        ("u_cmd", u_cmd), ("u_sat", u_sat)):
            log[name].append(v)
        self._integrate(d, t)
        self.tick += 1
        self._reading = self._measure()

    def result(self) -> dict[str, np.ndarray]:
        """The log so far: one array per :data:`LOG_COLUMNS` entry, one row per tick."""
        out = {k: np.asarray(v, dtype=float) for k, v in self._log.items()}
        for k in ("adc", "enc", "duty"):
            out[k] = out[k].astype(np.int64)
        return out


def _linear_rows(ctrl: Any) -> tuple[np.ndarray, np.ndarray]:
    # the controller's state estimate xh = Ez z + Ev v is linear: probe it once
    n = ctrl.n
    zero_z, zero_v = np.zeros(n), np.zeros(3)
    Ez = np.column_stack([ctrl.estimate(np.eye(n)[i], zero_v) for i in range(n)])
    Ev = np.column_stack([ctrl.estimate(zero_z, np.eye(3)[i]) for i in range(3)])
    return Ez, Ev


def run_scenario_float(
    scenario: Scenario,
    params: RobotParams,
    controller: Any,
    *,
    speed: str = "estimate",
    init: str = "zero",
    seed: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    plant: RobotParams | None = None,
    supply_measured: bool = False,
) -> dict[str, np.ndarray]:
    """Close the loop in pure simulation with the float discrete controller.

    Each tick: the delayed, noisy, quantised sensor counts of :class:`PlantSim` are decoded
    like the firmware does (ADC -> rad with offset and scale; 16-bit encoder unwrapped ->
    m), the controller (``host.design.discrete.DiscreteController``) computes ``u``, saturates it to
    ``u_max`` and updates its state with the saturated value; the force is mapped to an
    integer duty by the inverse motor model with back-EMF compensation
    (:func:`sim.motor.duty_from_force`), and the plant integrates that duty.

    Parameters
    ----------
    scenario : Scenario
        What happens during the run.
    params : RobotParams
        The design's robot parameters: the firmware side (count decoding, inverse motor
        model) uses them as they are -- the firmware knows neither the plant file nor the
        scenario's overrides -- and, without ``plant``, the plant with the scenario's
        overrides applied on top.
    controller : DiscreteController
        ``Cc, Dc, Ac, Bc, Bu, u_max`` and ``estimate(z, v)``.
    speed : {"estimate", "none"}
        Cart speed used for the back-EMF compensation: the controller's predicted state
        (``estimate(z, v)[1]``) or none (duty proportional to force).
    init : {"zero", "measured"}
        Initial controller state.  ``"zero"``: ``z = 0`` and positions measured from the
        encoder's zero.  ``"measured"``: as the firmware when balancing starts -- the cart
        position origin is the first encoder reading (``x_meas`` and the reference are taken
        relative to it), the estimate of the delayed tilt is the first ADC reading, speeds
        and stored forces are zero.
    seed : int, optional
        Noise seed overriding the scenario's.
    progress : callable, optional
        ``progress(tick, n_ticks)`` called every 100 ticks.
    plant : RobotParams, optional
        The simulated robot when it differs from the design (``--plant``); the scenario's
        ``[params]`` and delay are applied on top of it (:data:`sim.scenario.PRECEDENCE`).
    supply_measured : bool
        The firmware inverts the motor with the simulated robot's supply, as measured by the
        default board's divider (``firmware/motor.py`` ``Motor.set_supply``), instead of the
        design's ``V_supply`` (:func:`sim.batch.simulate_batch`, same option).

    Returns
    -------
    dict
        The run log (:data:`LOG_COLUMNS`), plus ``x_meas``, ``phi_meas`` and ``xdot_est``.
    """
    if speed not in ("estimate", "none"):
        raise ValueError(f"speed must be 'estimate' or 'none', got {speed!r}")
    if init not in ("zero", "measured"):
        raise ValueError(f"init must be 'zero' or 'measured', got {init!r}")
    sim = PlantSim(params if plant is None else plant, scenario, seed=seed)
    p = params  # the firmware's side: decoding and motor inversion with the design's values
    p_drive = p.replace(V_supply=sim.params.V_supply) if supply_measured else p
    Ac, Bc, Cc, Dc = (np.asarray(m, dtype=float) for m in (controller.Ac, controller.Bc, controller.Cc, controller.Dc))
    Bu = np.asarray(controller.Bu, dtype=float)[:, 0]
    umax = float(controller.u_max)
    Ez_v = _linear_rows(controller) if speed == "estimate" else None
    cpm = sensors.enc_counts_per_m(p)
    cpr = sensors.adc_counts_per_rad(p)
    off = p.pot_offset
    z = np.zeros(Ac.shape[0])
    adc0, enc0 = sim.read()
    # the firmware's 16-bit unwrap (sensors.EncoderUnwrapper), on plain ints
    total, last = int(sensors.encoder_delta(enc0, 0)), enc0
    x_origin = 0.0
    if init == "measured":
        x_origin = total / cpm
        total = 0
        z[2] = (adc0 - off) / cpr
    extra: dict[str, list[float]] = {"x_meas": [], "phi_meas": [], "xdot_est": []}
    n = sim.n_ticks
    # the firmware's set-point ramp (loop.ref_rate, its parameter ref_rate_mm_s): the controller's
    # reference moves to a new set-point at that speed; 0: at once
    ramp = float(p.values.get("loop.ref_rate", 0.0) or 0.0) * sim.Ts
    rq = sim.x_ref() - x_origin
    for k in range(n):
        adc, enc = sim.read()
        d = (enc - last) % sensors.ENC_MODULUS
        total += d - sensors.ENC_MODULUS if d >= sensors.ENC_MODULUS // 2 else d
        last = enc
        xm = total / cpm
        phm = (adc - off) / cpr
        rs = sim.x_ref() - x_origin
        rq = rs if ramp <= 0.0 else min(max(rs, rq - ramp), rq + ramp)
        v = np.array([xm, phm, rq])
        u = float(Cc[0] @ z + Dc[0] @ v)
        us = min(max(u, -umax), umax)
        xd_est = float(Ez_v[0][1] @ z + Ez_v[1][1] @ v) if Ez_v is not None else 0.0
        duty = int(motor.duty_from_force(us, xd_est, p_drive))
        z = Ac @ z + Bc @ v + Bu * us
        sim.step(duty, u_cmd=u, u_sat=us)
        extra["x_meas"].append(xm)
        extra["phi_meas"].append(phm)
        extra["xdot_est"].append(xd_est)
        if progress is not None and k % 100 == 0:
            progress(k, n)
    out = sim.result()
    out.update({k: np.asarray(v) for k, v in extra.items()})
    return out


def write_csv(log: Mapping[str, np.ndarray], path: str | Path) -> Path:
    """Write a run log as CSV (header row = column names; units in :data:`LOG_COLUMNS`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cols = list(log)
    n = len(log[cols[0]]) if cols else 0
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for i in range(n):
            w.writerow([_cell(log[c][i]) for c in cols])
    return path


def _cell(v: Any) -> str:
    if isinstance(v, (np.integer, int)):
        return str(int(v))
    return repr(float(v))


def read_csv(path: str | Path) -> dict[str, np.ndarray]:
    """Read a log written by :func:`write_csv` back into arrays."""
    with Path(path).open(newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise ValueError(f"{path}: empty CSV")
    head, body = rows[0], rows[1:]
    return {h: np.array([float(r[i]) for r in body]) for i, h in enumerate(head)}
