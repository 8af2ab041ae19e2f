"""Many scenarios through one HIL session: which to run, running them, and their files.

:func:`run_scenarios` runs a list of scenarios and writes, per scenario, the CSV log, a PNG
of the signals (with the float pure simulation overlaid when ``compare=True``) and a GIF;
it returns the :class:`~host.hil.results.HilRun` records whose summaries
:func:`sim.metrics.summary_table` prints.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

from host.hil.reference import float_reference
from host.hil.results import HilRun
from host.hil.session import HilSession
from sim.params import RobotParams, load_params
from sim.plantsim import write_csv
from sim.scenario import REPORT_SCENARIOS, Scenario, list_scenarios, load_scenario

__all__ = ["resolve_scenarios", "run_scenarios", "write_outputs"]


def resolve_scenarios(spec: str | Sequence[str]) -> list[Scenario]:
    """Scenarios from ``"all"`` (the report's), a name, a TOML path, or a list of those.

    Raises
    ------
    sim.scenario.ScenarioError
        Unknown name or invalid file (the message lists the known scenarios).
    """
    names: list[str]
    if isinstance(spec, str):
        names = [s for s in spec.split(",") if s] if spec != "all" else [n for n in REPORT_SCENARIOS if n in list_scenarios()]
    else:
        names = list(spec)
    return [load_scenario(n) for n in names]


def write_outputs(run: HilRun, out: str | Path, *, gif: bool = True, plot: bool = True) -> dict[str, Path]:
    """Write ``<name>.csv``, ``<name>.png`` and ``<name>.gif`` of a run into ``out``.

    Returns
    -------
    dict
        ``{"csv": path, "png": path, "gif": path}`` (those written).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    paths["csv"] = write_csv(run.log, out / f"{run.name}.csv")
    if plot or gif:
        from sim import plots

        summ = run.summary()
        label = f"HIL ({run.link}, {run.mode})"
        if plot:
            overlay = {"float simulation": run.reference} if run.reference is not None else None
            paths["png"] = plots.plot_run(run.log, out / f"{run.name}.png", run.params,
                                          title=f"{run.name}: firmware in the loop, {run.link} link, {run.mode}",
                                          overlay=overlay, label=label, settling_time=summ.metrics.settling_time)
        if gif:
            paths["gif"] = plots.animate_run(run.log, out / f"{run.name}.gif", run.params,
                                             title=f"{run.name} (firmware in the loop)")
    return paths


def run_scenarios(scenarios: Sequence[Scenario], *, port: str | None = None, link: str = "serial",
                  mode: str = "lockstep", out: str | Path | None = None, params: RobotParams | None = None,
                  compare: bool = False, gif: bool = True, plot: bool = True,
                  progress: Callable[[str, int, int], None] | None = None,
                  on_result: Callable[[HilRun], None] | None = None, plant: RobotParams | None = None,
                  **session_kw: Any) -> list[HilRun]:
    """Run scenarios through one HIL session and write their outputs.

    Parameters
    ----------
    scenarios : sequence of Scenario
        What to run, in order.
    port, link, mode
        See :class:`~host.hil.session.HilSession` (``port=None``: the virtual board).
    out : str or Path, optional
        Directory for CSV/PNG/GIF (nothing written when ``None``).
    params : RobotParams, optional
        The design's robot parameters (default ``sim/robot.toml``): the float reference's
        design and, without ``plant``, the simulated robot.
    compare : bool
        Also run the float pure simulation and keep it in ``HilRun.reference``.
    gif, plot : bool
        Write the GIF / PNG.
    progress : callable, optional
        ``progress(scenario_name, tick, n_ticks)``.
    on_result : callable, optional
        ``on_result(run)`` once a scenario has finished and its files are written (so an
        interrupted multi-scenario run still knows what finished).
    plant : RobotParams, optional
        The simulated robot when it differs from the design (``--plant``); the scenario's
        ``[params]`` are applied on top of it.  The firmware keeps its own gains.
    **session_kw
        Passed to :class:`~host.hil.session.HilSession`.
    """
    params = params or load_params()
    runs: list[HilRun] = []
    with HilSession(port, link=link, mode=mode, **session_kw) as sess:
        for sc in scenarios:
            cb = (lambda k, n, _name=sc.name: progress(_name, k, n)) if progress else None
            run = sess.run(sc, params if plant is None else plant, progress=cb)
            if compare:
                run.reference = float_reference(sc, params, plant=plant)
            if out is not None:
                run.stats["files"] = {k: str(v) for k, v in write_outputs(run, out, gif=gif, plot=plot).items()}
            runs.append(run)
            if on_result is not None:
                on_result(run)
    return runs
