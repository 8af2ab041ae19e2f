"""``make bench``: lockstep HIL throughput, serial and CAN, and where the time goes.

One scenario (``push_0p2N_5s``, 8 s simulated = 4000 ticks at 500 Hz) runs through the
virtual board (MicroPython unix port on a pty) in lockstep, per link:

* ``pipelined`` -- the runner's default: up to ``delay`` (5) sensor frames in flight, so
  the host's plant and the firmware work at the same time on the two cores;
* ``strict`` -- one frame at a time, where the times add up and split cleanly:
  ``plant`` (host: sensor model, RK4 sub-steps, log), ``firmware`` (the app's ``step()``,
  its own ``step_us`` from telemetry) and ``link`` (everything else: host encode/decode,
  pty, the firmware's frame decoding and answer).

The claim is the ratio to real time (goal >= 10x) and the split; absolute times move with
this shared machine's load.
"""

from __future__ import annotations

from typing import Any

__all__ = ["bench_hil"]

SCENARIO = "push_0p2N_5s"


def _row(run: Any, link: str, mode: str) -> dict[str, Any]:
    st = run.stats
    n = st["ticks"]
    wall_us = run.wall_s / n * 1e6
    plant = st["plant_s"] / n * 1e6
    fw = st["fw_step_us_mean"]
    row = {
        "link": link,
        "mode": mode,
        "x real time": run.realtime_factor,
        "us/tick": wall_us,
        "plant us": plant,
        "firmware us": fw,
        "link us": max(0.0, st["link_s"] / n * 1e6 - fw),
    }
    return row


def bench_hil() -> dict[str, Any]:
    """Lockstep HIL throughput (x real time) and its split, serial and CAN."""
    from host.hil.session import HilSession
    from sim.params import load_params
    from sim.scenario import load_scenario

    params = load_params()
    sc = load_scenario(SCENARIO)
    rows = []
    for link in ("serial", "can"):
        with HilSession(link=link) as sess:
            for mode, depth in (("pipelined", None), ("strict", 0)):
                run = sess.run_lockstep(sc, params, pipeline=depth)
                rows.append(_row(run, link, mode))
    notes = [
        f"scenario {SCENARIO}: {sc.duration:g} s simulated, {int(sc.duration * params.rate)} ticks at {params.rate:g} Hz",
        "x real time = simulated s / wall s of the closed loop (set-up excluded); goal >= 10x",
        "strict rows split a tick: plant (host RK4 + sensors) + firmware (app.step, MicroPython) + link (rest)",
        "pipelined: up to 5 sensor frames in flight (readings are 10 ms old, so already known); same results, bit for bit",
        "CAN frames travel as python-can 'serial' interface bytes; python-can reads them a few bytes per call",
    ]
    return {"title": "HIL lockstep throughput (virtual board, MicroPython unix port on a pty)", "rows": rows,
            "notes": notes}
