"""The virtual robot: the simulated robot on the emulated Pico's pins, and a person's hands.

``upright emulate rp2040 --pty`` (and ``--can``) closes the plant of ``hil --emulate`` around
the board running ``main.py`` -- :class:`sim.plantsim.PlantSim` with the project's sensor
model, on the pins as ``firmware/board.py`` wires them (:class:`host.hil.emulated.PinDrive`:
ADC0 from the pot reading, quadrature edges from the cart position, the duty read from
PWM/DIR/EN) -- so that every board tool works against it as against a real robot.

Time is the board's: each plant tick is one run of :data:`OVERSAMPLE` ticks per control period
of emulated time (2 kHz at the 500 Hz loop: the firmware samples a reading at most 0.5 ms old,
as from continuous sensors, whatever the phase of its loop), the duty the H-bridge applied
over that run (averaged) drives the next.  The emulator runs slower than real time (about
0.1-0.2x here), so host tools see a slower robot, never an inconsistent one.

A person stands by (:class:`Hand`): at start the pendulum is held upright at rest, the cart
still, until the board drives its motor (EN high: the firmware enables the driver only while
balancing) -- "hold the pendulum upright, then arm; let go gently".  When the motor goes off
(a disarm, a fault) the person catches the pendulum and the cart and holds them the same way,
so the next tool can arm again; one that lies on its stop otherwise (let go by ``release``) is
picked up after :data:`CATCH_S`.  Everything else a person does is asked for through :class:`host.hil.hands.HandsServer`, a Unix
socket at :func:`host.hil.hands.hands_path` of the port (the path is derived from the port, so a tool given
only ``--port`` finds it; a real robot has none): one JSON object per line each way,
``{"do": ACTION, ...}`` -> ``{"ok": true, ...}`` (or ``{"ok": false, "error": ...}``), the
answer sent once the action is done and :data:`SETTLE_S` of board time has passed (the
readings the board gets are delayed: ``sensors.delay``).  Actions (:data:`ACTIONS`):

``hello``
    who answers: ``port``, ``plant`` (the robot file), ``board_s``, ``actions``.
``state``
    the true state ``x, xdot, phi, phidot``, ``hand``, ``pendulum``, ``driving``, ``board_s``.
``hold``
    ``phi`` (rad, default 0; positive leans backward, towards -x: the model's convention),
    ``cart`` (``"still"`` held, or ``"free"``: the wheels lifted -- they turn as the motor drives
    them and the encoder counts it), ``until`` (``"driving"``: let go when the driver is enabled),
    ``seconds`` (board time to hold before answering); answers ``moved_m`` (encoder-side travel).
``move``
    ``dx`` (m, positive = forward = +x), ``seconds`` (board time, default 0.4): rolls the cart by
    ``dx`` with the pendulum held; answers ``moved_m``.
``release``
    let go of pendulum and cart.
``pendulum``
    ``on`` false: take the pendulum off (the cart alone, the pot at its upright reading);
    true: put it back, held upright until the board drives.
``wait``
    ``seconds`` of board time.
``reset``
    power-cycle the board (the flash kept: saved parameters and gains stay); answers once it
    has booted again.

:class:`host.hil.hands.Hands` is the client (``upright board calibrate --robot auto`` uses it).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable

from host.boards.rp2040.board import CYCLES_PER_US, StepResult
from host.hil.emulated import PinDrive
from sim import motor
from sim.params import RobotParams
from sim.plantsim import PlantSim
from sim.scenario import Scenario

__all__ = ["OVERSAMPLE", "SETTLE_S", "CATCH_S", "ACTIONS", "Hand", "RobotPlant", "VirtualRobot", "serve"]

OVERSAMPLE = 4
"""Plant ticks per control period (the plant runs at this multiple of ``loop.rate``)."""
SETTLE_S = 0.05
"""Board seconds an action waits once done before it answers (longer than the sensor delay)."""
CATCH_S = 0.3
"""Board seconds a fallen pendulum lies (driver off) before the person picks it up."""
ACTIONS = ("hello", "state", "hold", "move", "release", "pendulum", "wait", "reset")
_HALF_PI = 0.5 * math.pi


@dataclass
class Hand:
    """What the person's hands do: hold the pendulum at ``phi`` at rest; the cart ``"still"``,
    ``"free"`` (wheels lifted) or ``"move"`` (rolled from ``x0`` to ``x1`` over board time
    ``t0 .. t1``); ``until_driving``: let go when the board drives its motor."""

    phi: float = 0.0
    cart: str = "still"
    until_driving: bool = False
    x0: float = 0.0
    x1: float = 0.0
    t0: float = 0.0
    t1: float = 0.0

    def describe(self) -> dict[str, Any]:
        """The hand as JSON."""
        return {"phi": self.phi, "cart": self.cart, "until": "driving" if self.until_driving else None}


class RobotPlant(PlantSim):
    """:class:`PlantSim` with a person's hands on it and no per-tick log (it runs for hours).

    Free: the plant's own equations (:meth:`PlantSim.step`'s RK4); the drive's force only while the
    H-bridge is enabled (``driven``).  Held (:attr:`hand`): the
    pendulum at the hand's angle and at rest, the cart still, rolled, or free -- then the cart
    and the held pendulum move together under the motor force and the friction (exact for the
    linear drive: ``(M + m) xdd = a duty - (c + b) xd``).  Pendulum off (:attr:`pendulum_on`
    false): the cart alone, ``M xdd = a duty - (c + b) xd`` (with the robot file's plant realism --
    Coulomb and static friction, gear play, deadband, minimum duty -- :class:`PlantSim`'s own
    integrator with the pendulum's mass off), the pot at its upright reading.
    """

    def __init__(self, params: RobotParams, *, seed: int = 0) -> None:
        sc = Scenario(name="virtual_robot", duration=1e6, seed=seed, source="<virtual robot>")
        super().__init__(params, sc, ground_stop=True)
        self.hand: Hand | None = Hand(until_driving=True)
        self.pendulum_on = True
        self.duty = 0

    def _cart(self, duty: int, mass: float) -> None:
        x = self._x
        k = (self._c_emf + self._b) / mass
        f = self._a_duty * duty / mass
        T = self.Ts
        if k <= 0:
            x[0] += x[1] * T + 0.5 * f * T * T
            x[1] += f * T
            return
        v_inf = f / k
        e = math.exp(-k * T)
        x[0] += v_inf * T + (x[1] - v_inf) * (1.0 - e) / k
        x[1] = v_inf + (x[1] - v_inf) * e

    def _cart_real(self, duty: int) -> None:
        # the cart alone with plant realism: PlantSim's integrator with no pendulum (m L = 0:
        # the cart's row is M xdd = F - b xd, the pendulum's is 0)
        m, mL = self._m, self._mL
        self._m = self._mL = 0.0
        self._x[2] = self._x[3] = 0.0
        try:
            self._integrate(duty, self.t)
        finally:
            self._m, self._mL = m, mL

    def step(self, duty: int, *, u_cmd: float = math.nan, u_sat: float = math.nan, driven: float = 1.0) -> None:
        """Apply ``duty`` for one plant tick (hands and pendulum as they are) and take the next reading.

        ``driven``: the fraction of the tick the H-bridge was enabled (EN high), as
        :meth:`PlantSim.step` takes it.  Disabled (EN low), its outputs float -- no current, so
        no force and no back-EMF braking (the coast-down of ``excite --cart-only``); at duty 0
        with the bridge enabled the motor is shorted and brakes (:func:`sim.motor.force_from_duty`).
        """
        frac = min(1.0, max(0.0, float(driven)))
        d = min(max(int(duty), -motor.DUTY_MAX), motor.DUTY_MAX) if frac > 0.0 else 0
        self.duty = d
        ce = self._c_emf
        if frac != 1.0:
            self._c_emf = ce * frac
        try:
            self._step(d)
        finally:
            self._c_emf = ce

    def _step(self, d: int) -> None:
        hand = self.hand
        x = self._x
        if not self.pendulum_on:
            if self._real:  # dry friction, gear play, the bridge's deadband: the plant's own
                self._cart_real(d)  # integrator with the pendulum's mass taken off
            else:
                self._cart(d, self._M)
            x[2] = x[3] = 0.0
        elif hand is None:
            self._integrate(d, self.t)
        else:
            if hand.cart == "free":
                self._cart(d, self._M + self._m)
            elif hand.cart == "move":
                t1 = self.t + self.Ts
                span = max(hand.t1 - hand.t0, 1e-9)
                s = min(1.0, max(0.0, (t1 - hand.t0) / span))
                x[0] = hand.x0 + (hand.x1 - hand.x0) * s
                x[1] = (hand.x1 - hand.x0) / span if s < 1.0 else 0.0
            else:
                x[1] = 0.0
            x[2], x[3] = hand.phi, 0.0
        self.tick += 1
        self._reading = self._measure()

    @property
    def lying(self) -> bool:
        """The pendulum lies on its stop (fell to horizontal)."""
        return self.pendulum_on and abs(self._x[2]) >= _HALF_PI - 1e-9


_Done = Callable[[dict[str, Any]], None]


class VirtualRobot:
    """The simulated robot on a board's pins, and the person's hands (module docstring).

    Parameters
    ----------
    plant : RobotParams
        The robot simulated (``--plant``; default the design, ``sim/robot.toml``).
    oversample : int
        Plant ticks per control period.
    seed : int
        Seed of the (unused unless the plant file says so) noise generator.
    catch : bool
        The stand-by person catches the pendulum when the motor goes off, and picks up a fallen one
        (:data:`CATCH_S`).
    """

    def __init__(self, plant: RobotParams, *, oversample: int = OVERSAMPLE, seed: int = 0,
                 catch: bool = True) -> None:
        self.params = plant
        self.plant = RobotPlant(plant.replace(rate=plant.rate * int(oversample)), seed=seed)
        self.tick_us = 1e6 * self.plant.Ts
        self.catch = bool(catch)
        self.board: Any = None
        self.pins: PinDrive | None = None
        self._pending: list[tuple[float, Callable[[], dict[str, Any]], _Done]] = []
        self.reset_wanted: list[_Done] = []
        self._lying_since: float | None = None
        self._was_driving = False
        self._moved_from = 0.0

    # ------------------------------------------------------------------ the board side
    def attach(self, board: Any) -> None:
        """Wire to ``board`` (an :class:`~host.boards.rp2040.board.EmulatedBoard`): the robot's
        supply on the divider pin, the pins from the next :meth:`before` on (also after a reset)."""
        from firmware import board as fb

        self.board = board
        if self.pins is None or self.pins.board is not board:
            self.pins = PinDrive(board, enc_within_us=min(40.0, self.tick_us / 4), lazy=True)
        if int(getattr(fb, "VSUP_ADC_PIN", -1)) >= 26:
            board.set_supply_mv(1000.0 * float(self.params.V_supply))

    @property
    def board_s(self) -> float:
        """Board time (s since the board's power-on)."""
        return self.plant.t

    def before(self) -> None:
        """Put the current reading on the pins."""
        assert self.pins is not None
        self.pins.set(*self.plant.read())

    def after(self, r: StepResult, c0: int) -> None:
        """The duty the board applied during run ``r`` (from cycle ``c0``) drives one plant tick;
        then the stand-by person's rules and the actions that are due."""
        assert self.pins is not None
        duty = self.pins.duty(r, c0, r.cycles)
        p = self.plant
        driving = self.pins.driving
        p.step(int(round(duty)), driven=self.pins.en_fraction)  # EN low: the motor coasts
        hand = p.hand
        if hand is not None:
            if hand.until_driving and driving:
                p.hand = None  # let go gently: the board balances
            elif hand.cart == "move" and p.t >= hand.t1:
                hand.cart, p._x[0], p._x[1] = "still", hand.x1, 0.0
        elif self.catch and self._was_driving and not driving and p.pendulum_on:
            p.hand = Hand(until_driving=True)  # the motor went off: caught, stood upright, the cart held
            p._x[1] = 0.0
        elif self.catch and p.lying and not driving:
            if self._lying_since is None:
                self._lying_since = p.t
            elif p.t - self._lying_since >= CATCH_S:
                p.hand = Hand(until_driving=True)  # picked up, held upright, the cart still
                self._lying_since = None
        else:
            self._lying_since = None
        self._was_driving = driving
        while self._pending and self._pending[0][0] <= p.t:
            _, answer, done = self._pending.pop(0)
            done(answer())

    def power_cycled(self) -> None:
        """The board was powered up again: its pins start from scratch -- its encoder counter at
        0, followed from there by the cart's travel since the reset (:meth:`PinDrive.rebase`; a
        fresh :class:`PinDrive` would take the plant's whole 16-bit reading as one jump, a burst
        of up to 32767 edges that the firmware, already reading, latches as ``enc_jump``)."""
        assert self.pins is not None
        self.pins.rebase()
        self.attach(self.board)

    # ------------------------------------------------------------------ the hands
    def state(self) -> dict[str, Any]:
        """The true state and what the hands do."""
        p = self.plant
        x = p._x
        return {"board_s": p.t, "x": x[0], "xdot": x[1], "phi": x[2], "phidot": x[3],
                "hand": p.hand.describe() if p.hand else None, "pendulum": "on" if p.pendulum_on else "off",
                "driving": bool(self.pins.driving) if self.pins else False, "duty": p.duty, "lying": p.lying}

    def _later(self, seconds: float, answer: Callable[[], dict[str, Any]], done: _Done) -> None:
        self._pending.append((self.plant.t + max(0.0, seconds), answer, done))
        self._pending.sort(key=lambda e: e[0])

    def _moved(self) -> Callable[[], dict[str, Any]]:
        x0 = self.plant._x[0]
        return lambda: {"ok": True, "moved_m": self.plant._x[0] - x0, **self.state()}

    def handle(self, req: dict[str, Any], done: _Done) -> None:
        """Do one action (module docstring); ``done(answer)`` is called when it is done."""
        try:
            self._handle(req, done)
        except (KeyError, TypeError, ValueError) as exc:
            done({"ok": False, "error": str(exc)})

    def _handle(self, req: dict[str, Any], done: _Done) -> None:
        p = self.plant
        act = req.get("do")

        def num(key: str, default: float, lo: float, hi: float) -> float:
            v = float(req.get(key, default))
            if not (lo <= v <= hi):
                raise ValueError(f"{act}: {key} must be within {lo:g} .. {hi:g}, got {v!r}")
            return v

        if act == "hello":
            done({"ok": True, "robot": "virtual", "port": getattr(self, "port", None), "plant": self.params.source,
                  "board_s": p.t, "actions": list(ACTIONS)})
        elif act == "state":
            done({"ok": True, **self.state()})
        elif act == "hold":
            cart = req.get("cart", "still")
            if cart not in ("still", "free"):
                raise ValueError(f"hold: cart must be 'still' or 'free', got {cart!r}")
            until = req.get("until")
            if until not in (None, "driving"):
                raise ValueError(f"hold: until must be 'driving' or null, got {until!r}")
            phi = num("phi", 0.0, -_HALF_PI, _HALF_PI)
            secs = num("seconds", 0.0, 0.0, 60.0)
            p.pendulum_on = True
            answer = self._moved()
            p.hand = Hand(phi=phi, cart=cart, until_driving=until == "driving")
            if cart == "still":
                p._x[1] = 0.0
            self._later(max(secs, SETTLE_S), answer, done)
        elif act == "move":
            dx = num("dx", 0.0, -2.0, 2.0)
            secs = num("seconds", 0.4, 0.01, 60.0)
            answer = self._moved()
            phi = p.hand.phi if p.hand is not None else 0.0
            x0 = p._x[0]
            p.hand = Hand(phi=phi, cart="move", x0=x0, x1=x0 + dx, t0=p.t, t1=p.t + secs)
            self._later(secs + SETTLE_S, answer, done)
        elif act == "release":
            p.hand = None
            done({"ok": True, **self.state()})
        elif act == "pendulum":
            on = bool(req.get("on", True))
            p.pendulum_on = on
            p._x[2] = p._x[3] = 0.0
            p.hand = Hand(until_driving=True) if on else None
            self._later(SETTLE_S, lambda: {"ok": True, **self.state()}, done)
        elif act == "wait":
            self._later(num("seconds", 0.0, 0.0, 600.0), lambda: {"ok": True, **self.state()}, done)
        elif act == "reset":
            self.reset_wanted.append(done)
        else:
            raise ValueError(f"unknown action {act!r} (actions: {', '.join(ACTIONS)})")


def serve(link: Any, robot: VirtualRobot, stop: Callable[[], bool], hands: Any = None, *,
          poll_every: int = 4) -> None:
    """Run the board with the robot on its pins until ``stop()`` is true, never faster than real time.

    ``link`` is a :class:`~host.boards.rp2040.bridge.PtyBridge` or a
    :class:`~host.boards.rp2040.can.CanBoard`: ``run(us)`` moves the host link's bytes or frames
    and runs the board; ``link.board`` is the :class:`~host.boards.rp2040.board.EmulatedBoard`.

    Raises
    ------
    BoardError
        The board raised or stopped (quoting its last output).
    """
    board = link.board
    robot.attach(board)
    t0, c0 = time.monotonic(), board.cycles
    k = 0
    while not stop():
        robot.before()
        c = board.cycles
        r = link.run(robot.tick_us)
        robot.after(r, c)
        k += 1
        if hands is not None and k % poll_every == 0:
            hands.poll()
        if robot.reset_wanted:
            board.reset()
            robot.power_cycled()
            # board time starts again at 0 on the chip; the robot's own clock runs on
            for done in robot.reset_wanted:
                done({"ok": True, **robot.state()})
            robot.reset_wanted.clear()
            t0, c0 = time.monotonic(), board.cycles
        ahead = (board.cycles - c0) / (CYCLES_PER_US * 1e6) - (time.monotonic() - t0)
        if ahead > 0.005:
            time.sleep(ahead)


