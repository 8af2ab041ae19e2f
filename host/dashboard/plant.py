"""``upright dashboard --virtual``: the firmware on a pty, closed around the simulated plant, live.

:class:`VirtualPlant` opens a :class:`host.hil.session.HilSession` on the virtual board (the
firmware's HIL main under the MicroPython unix port on a pty, lockstep mode), brings it to a
clean, *disarmed* start (:meth:`~host.hil.session.HilSession.prepare`: faults cleared, the
arm threshold opened, reference 0) and then runs THE lockstep loop
(:class:`host.hil.lockstep.Lockstep`) in a background thread, paced to the wall clock (one
tick per control period: the pendulum moves in real time), in chunks of :attr:`chunk_s` of
plant time, each chunk continuing from the last one's state.  Every message the board sends
besides its loop answers -- telemetry, heartbeats, replies to the page's commands -- goes to
the dashboard's :class:`~host.dashboard.hub.Hub`.

The pendulum starts upright and at rest.  Disarmed, nothing holds it: once tilted it falls and
lies on the ground; :meth:`VirtualPlant.reset` (the page's "pendulum upright" button, only
while the motor is off) stands it up again where the cart is, as a hand would.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from host.dashboard.hub import Hub
from host.hil.accounting import Sink
from host.hil.errors import HilError
from host.hil.lockstep import Lockstep
from host.hil.session import HilSession
from host.link.clients import Link, LinkError
from sim.params import RobotParams, load_params
from sim.plantsim import PlantSim
from sim.scenario import scenario_from_dict

__all__ = ["VirtualPlant"]


class _Restart(Exception):
    """Ends a lockstep chunk early (stop, or the pendulum put back upright)."""


class _HubSink(Sink):
    # every message of the loop that is not an answer goes to the hub, stamped on arrival
    def __init__(self, hub: Hub, link: Any) -> None:
        super().__init__(link, strict=False)
        self.hub = hub

    def other(self, m: Any, tick: int = -1) -> None:
        self.hub.on_message(m, getattr(self._link, "last_seq", None), time.time())


class VirtualPlant:
    """The virtual board and the simulated robot, run in real time for the dashboard.

    Parameters
    ----------
    params : RobotParams, optional
        Robot parameters (default ``sim/robot.toml``).
    chunk_s : float
        Plant seconds per lockstep run (the loop continues from the last state).
    timeout : float
        Seconds to wait for any answer of the firmware.
    """

    def __init__(self, params: RobotParams | None = None, *, chunk_s: float = 60.0, timeout: float = 2.0) -> None:
        self.params = params or load_params()
        self.scenario = scenario_from_dict({"name": "dashboard", "duration": float(chunk_s),
                                            "description": "live dashboard run"})
        self.session = HilSession(None, link="serial", mode="lockstep", rt_priority=None, timeout=timeout)
        self.hub: Hub | None = None
        self.error: str | None = None
        self.ticks = 0
        self.behind_s = 0.0
        self.fw_state = -1
        self.fw_duty = 0
        self._state = [0.0, 0.0, 0.0, 0.0]
        self._stop = threading.Event()
        self._upright = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def gains(self) -> dict[str, Any]:
        """The table the board runs at start: the firmware's own."""
        from firmware import gains as G

        return {"crc": int(G.CRC), "label": f"{self.session.gains} (firmware/gains.py)"}

    def open(self) -> Link:
        """Start the virtual board and bring it to a disarmed start; returns its link (for the hub)."""
        self.session.open()
        sim = PlantSim(self.params, self.scenario, x0=self._state)
        self.session.prepare(sim, Sink(self.session.link, strict=False), arm=False)
        return self.session.link  # type: ignore[return-value]

    def start(self, hub: Hub) -> "VirtualPlant":
        """Run the paced lockstep loop in a background thread, messages to ``hub``."""
        self.hub = hub
        self._thread = threading.Thread(target=self._run, name="dashboard-plant", daemon=True)
        self._thread.start()
        return self

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def reset(self) -> None:
        """Stand the pendulum up (at rest, where the cart is) at the next tick."""
        self._upright.set()

    def _run(self) -> None:
        hub = self.hub
        assert hub is not None
        link = self.session.link
        assert link is not None
        link.share(threading.current_thread())  # the loop reads; the hub's commands wait for what it delivers
        sink = _HubSink(hub, link)
        Ts = 1.0 / self.params.rate
        clock = time.perf_counter
        t_start = clock()
        done = 0
        while not self._stop.is_set():
            sim = PlantSim(self.params, self.scenario, x0=self._state)
            base = done

            def pace(tick: int, sim: PlantSim = sim, base: int = base) -> None:
                nonlocal t_start
                if self._stop.is_set() or self._upright.is_set():
                    raise _Restart
                target = t_start + (base + tick) * Ts
                lag = clock() - target
                if lag > 0.2:  # fell behind (a busy machine): skip the time, never burst
                    t_start += lag
                    self.behind_s += lag
                elif lag < 0:
                    time.sleep(-lag)
                self.ticks = base + tick

            try:
                Lockstep(self.session, sim, sink=sink, depth=0, on_tick=pace, after_tick=self._answer,
                         record=False).run()
            except _Restart:
                pass
            except (HilError, LinkError, OSError) as exc:
                if not self._stop.is_set():
                    self.error = f"virtual board stopped: {exc}"
                    hub.note(self.error)
                return
            done += sim.tick
            x = [float(v) for v in sim.state]
            if self._upright.is_set():
                self._upright.clear()
                x = [x[0], 0.0, 0.0, 0.0]
                hub.note("virtual pendulum stood upright")
            self._state = x

    def _answer(self, tick: int, m: Any) -> None:
        # the firmware's own answer of every tick: its state and duty, straight off the link
        if m is not None:
            self.fw_state = m.state
            self.fw_duty = m.duty

    def status(self) -> dict[str, Any]:
        """The loop's figures: ticks run, seconds skipped when behind, the last answer's state and duty."""
        return {"ticks": self.ticks, "behind_s": round(self.behind_s, 3), "fw_state": self.fw_state,
                "fw_duty": self.fw_duty, "error": self.error}

    def stop(self) -> None:
        """End the loop and the virtual board."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self.session.close()
