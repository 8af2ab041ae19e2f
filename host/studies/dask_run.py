"""Scale-out of the batch sweeps on a Dask cluster.

A sweep is already a list of independent tasks ``(SweepConfig, start, stop)``
(:func:`host.studies.sweep.tasks_for`) whose results depend only on the configuration and the
run indices (seeds are per run, never per task), so the cluster computes exactly the
tables a single process would; this module only ships the tasks and gathers the tables
in task order.

Usage::

    upright sweep robustness --n 100000 --scheduler tcp://10.0.0.5:8786

or from Python ``run_on_dask(tasks, "tcp://...", run_task)`` / ``run_on_dask(tasks, client, run_task)``.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

__all__ = ["DaskRunError", "check_reachable", "run_on_dask"]


class DaskRunError(RuntimeError):
    """The cluster could not be reached or a task failed on it."""


def check_reachable(address: str, timeout: float = 10.0) -> None:
    """Fail fast when nothing listens at a ``tcp://HOST:PORT`` scheduler address (a refused
    connection is known at once; the Dask client would retry until its timeout).

    Raises
    ------
    DaskRunError
        The address is malformed or the connection is refused or times out.
    """
    import socket
    from urllib.parse import urlsplit

    if not address.startswith("tcp://"):
        return
    try:
        u = urlsplit(address)
        host, port = u.hostname, u.port
    except ValueError as exc:
        raise DaskRunError(f"bad Dask scheduler address {address!r}: {exc}") from exc
    if not host or port is None:
        raise DaskRunError(f"bad Dask scheduler address {address!r}: expected tcp://HOST:PORT")
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as exc:
        raise DaskRunError(f"cannot reach the Dask scheduler at {address!r}: {exc.strerror or exc}") from exc


def run_on_dask(
    tasks: Sequence[tuple[Any, int, int]],
    scheduler: Any,
    fn: Callable[[Any, int, int], dict[str, np.ndarray]],
    *,
    progress: Callable[[int, int], None] | None = None,
    on_result: Callable[[int, dict[str, np.ndarray]], None] | None = None,
    timeout: float = 10.0,
) -> list[dict[str, np.ndarray]]:
    """Run sweep tasks on a Dask cluster; the tables in task order.

    Parameters
    ----------
    tasks : sequence of (SweepConfig, int, int)
        Tasks from :func:`host.studies.sweep.tasks_for`.
    scheduler : str or distributed.Client
        Scheduler address (``"tcp://host:8786"``) or a connected client.
    fn : callable
        ``fn(cfg, start, stop) -> table``, a module-level function the workers can import
        (:func:`host.studies.sweep.run_task`); passed in so this module needs no sweep.
    progress : callable, optional
        ``progress(runs_done, runs_total)`` after each finished task.
    on_result : callable, optional
        ``on_result(task_index, table)`` as each task finishes (in completion order), so a
        caller interrupted mid-sweep keeps what finished.
    timeout : float
        Seconds to wait for the connection to the scheduler.

    Returns
    -------
    list of dict
        One table per task, in the order of ``tasks``.

    Raises
    ------
    DaskRunError
        If the scheduler cannot be reached or a task raises on a worker (chained).
    """
    if isinstance(scheduler, str):
        check_reachable(scheduler, timeout)
    from distributed import Client, as_completed

    own = not isinstance(scheduler, Client)
    futures: list[Any] = []
    try:
        client = Client(scheduler, timeout=timeout) if own else scheduler
    except (OSError, TimeoutError) as exc:
        raise DaskRunError(f"cannot reach the Dask scheduler at {scheduler!r}: {exc}") from exc
    try:
        total = sum(b - a for _, a, b in tasks)
        futures = [client.submit(fn, cfg, a, b, pure=False) for cfg, a, b in tasks]
        index = {f.key: i for i, f in enumerate(futures)}
        out: list[dict[str, np.ndarray] | None] = [None] * len(futures)
        done = 0
        if progress is not None:
            progress(0, total)
        for fut in as_completed(futures):
            i = index[fut.key]
            try:
                out[i] = fut.result()
            except Exception as exc:  # noqa: BLE001 - re-raised with context
                raise DaskRunError(f"sweep task {i} (runs {tasks[i][1]}..{tasks[i][2]}) failed: {exc}") from exc
            if on_result is not None:
                on_result(i, out[i])  # type: ignore[arg-type]
            done += tasks[i][2] - tasks[i][1]
            if progress is not None:
                progress(done, total)
        return [t for t in out if t is not None]
    except KeyboardInterrupt:
        for f in futures:
            f.cancel()
        raise
    finally:
        if own:
            client.close()
