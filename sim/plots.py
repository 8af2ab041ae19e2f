"""Figures of a run: a PNG of the signals with the constraint bands, an animated GIF of the robot.

Both take a run log (:data:`sim.plantsim.LOG_COLUMNS`: ``t, x, phi, x_ref, force, f_dist,
xddot`` ...) and use matplotlib's non-interactive Agg backend, so they work on a headless
machine and in CI.

* :func:`plot_run` -- four panels sharing the time axis: tilt ``phi`` with the +-phi_max
  band, cart position with its reference, motor (and disturbance) force with the drive's
  stall-force limit, cart acceleration with the +-a_max band; optional overlays (e.g. the
  float reference on top of the HIL run) and a marker at the settling time.
* :func:`animate_run` -- the cart on its track and the pendulum, with the reference marked,
  written as a GIF with :class:`matplotlib.animation.PillowWriter`; frames are decimated to
  ``fps`` (default 15/s) and capped at ``max_frames`` (default 120) so a run renders in ~2 s.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import animation  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from .metrics import Metrics  # noqa: E402
from .motor import stall_force  # noqa: E402
from .params import RobotParams  # noqa: E402

__all__ = ["plot_run", "animate_run", "FastPillowWriter"]

Log = Mapping[str, np.ndarray]


class FastPillowWriter(animation.PillowWriter):
    """:class:`~matplotlib.animation.PillowWriter` that grabs the already-drawn canvas.

    ``Animation.save`` draws every frame (``draw_idle``, a full draw on Agg) and the stock
    writer then draws it a second time in ``savefig``; this one copies the Agg buffer
    instead, halving the rendering time of a GIF, and reduces each frame to a 64-colour
    palette with Pillow's fast octree quantiser.
    """

    def grab_frame(self, **savefig_kwargs) -> None:  # noqa: ANN003 - matplotlib's signature
        from PIL import Image

        canvas = self.fig.canvas  # drawn by Animation._draw_next_frame (draw_idle = draw on Agg)
        buf = canvas.buffer_rgba()
        w, h = canvas.get_width_height(physical=True)
        rgb = Image.frombuffer("RGBA", (w, h), bytes(buf), "raw", "RGBA", 0, 1).convert("RGB")
        # palette now, with the fast octree quantiser (the GIF encoder's default is ~10x slower)
        self._frames.append(rgb.quantize(colors=64, method=Image.Quantize.FASTOCTREE))


def _band(ax, lim: float, label: str) -> None:  # noqa: ANN001 - matplotlib Axes
    # shade outside +-lim up to the current y limits (call after the limits are set)
    lo, hi = ax.get_ylim()
    if hi > lim:
        ax.axhspan(lim, hi, color="tab:red", alpha=0.10, lw=0)
    if lo < -lim:
        ax.axhspan(lo, -lim, color="tab:red", alpha=0.10, lw=0)
    ax.axhline(lim, color="tab:red", lw=0.8, ls="--", label=label)
    ax.axhline(-lim, color="tab:red", lw=0.8, ls="--")
    ax.set_ylim(lo, hi)


def _ylim(ax, data: list[np.ndarray], lim: float | None) -> None:  # noqa: ANN001
    vals = np.concatenate([np.asarray(d, dtype=float).ravel() for d in data])
    vals = vals[np.isfinite(vals)]
    top = float(np.max(np.abs(vals))) if vals.size else 1.0
    if lim is not None:
        top = max(top, lim)
    top = top * 1.15 if top > 0 else 1.0
    ax.set_ylim(-top, top)


def plot_run(
    log: Log,
    path: str | Path,
    params: RobotParams,
    *,
    title: str = "",
    overlay: Mapping[str, Log] | None = None,
    label: str = "run",
    metrics: Metrics | None = None,
    settling_time: float | None = None,
    settle_from: float = 0.0,
) -> Path:
    """Write a PNG of tilt, cart position, force and acceleration with the constraint bands.

    Parameters
    ----------
    log : mapping of arrays
        The run log.
    path : str or Path
        Output PNG (parent directories are created).
    params : RobotParams
        For the constraint values (phi_max, a_max) and the drive's stall force.
    title : str
        Figure title.
    overlay : mapping of str to log, optional
        Other runs drawn thinner on top, by label (e.g. ``{"float": float_log}``).
    label : str
        Legend label of ``log``.
    metrics : Metrics, optional
        The run's metrics: the settling instant (end of the worst settling segment) is
        marked with a vertical line.
    settling_time, settle_from : float, optional
        The same mark given by hand (``settle_from + settling_time``), when ``metrics`` is
        not given.

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    runs = {label: log, **(overlay or {})}
    t = np.asarray(log["t"], dtype=float)
    fig, axes = plt.subplots(4, 1, figsize=(9, 9.5), sharex=True, constrained_layout=True)
    ax_phi, ax_x, ax_f, ax_a = axes
    styles = [dict(lw=1.4), dict(lw=0.9, ls="--"), dict(lw=0.9, ls=":"), dict(lw=0.9, ls="-.")]
    for (name, lg), st in zip(runs.items(), styles * 4):
        tt = np.asarray(lg["t"], dtype=float)
        ax_phi.plot(tt, lg["phi"], label=f"phi ({name})", **st)
        ax_x.plot(tt, lg["x"], label=f"x ({name})", **st)
        ax_f.plot(tt, lg["force"], label=f"motor force ({name})", **st)
        ax_a.plot(tt, lg["xddot"], label=f"cart accel. ({name})", **st)
    # tilt
    _ylim(ax_phi, [lg["phi"] for lg in runs.values()], params.phi_max)
    _band(ax_phi, params.phi_max, f"|phi| < {params.phi_max:g} rad")
    ax_phi.set_ylabel("tilt phi (rad)")
    if metrics is not None:
        settling_time, settle_from = metrics.settling_time, metrics.settle_from
    if settling_time is not None and math.isfinite(settling_time):
        ts = settling_time
        for ax in axes:
            ax.axvline(settle_from + ts, color="tab:green", lw=0.8, ls=":")
        ax_phi.plot([], [], color="tab:green", ls=":", label=f"settled ({ts:.2f} s after {settle_from:g} s; limit {params.t_settle:g} s)")
    # cart
    if "x_ref" in log:
        ax_x.step(t, log["x_ref"], where="post", color="k", lw=0.9, ls="--", label="reference")
    ax_x.set_ylabel("cart x (m)")
    # force
    if "f_dist" in log and np.any(np.asarray(log["f_dist"]) != 0):
        ax_f.plot(t, log["f_dist"], color="tab:purple", lw=0.9, label="disturbance")
    fs = float(stall_force(params))
    peak_f = max(float(np.nanmax(np.abs(np.asarray(lg["force"], dtype=float)))) for lg in runs.values())
    if fs <= 1.5 * peak_f:  # the drive's limit is shown when the force comes near it
        ax_f.axhline(fs, color="0.5", lw=0.8, ls="--", label=f"stall force {fs:.0f} N")
        ax_f.axhline(-fs, color="0.5", lw=0.8, ls="--")
        _ylim(ax_f, [lg["force"] for lg in runs.values()], fs)
    else:
        ax_f.plot([], [], color="0.5", lw=0.8, ls="--", label=f"stall force {fs:.0f} N (off scale)")
        _ylim(ax_f, [lg["force"] for lg in runs.values()], None)
    ax_f.set_ylabel("force (N)")
    # acceleration
    _ylim(ax_a, [lg["xddot"] for lg in runs.values()], params.a_max)
    _band(ax_a, params.a_max, f"|xddot| <= {params.a_max:g} m/s^2")
    ax_a.set_ylabel("cart accel. (m/s^2)")
    ax_a.set_xlabel("time (s)")
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(loc="upper right", fontsize=7, ncol=2)
        ax.set_xlim(t[0], t[-1])
    if title:
        fig.suptitle(title)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def animate_run(
    log: Log,
    path: str | Path,
    params: RobotParams,
    *,
    title: str = "",
    fps: int = 15,
    max_frames: int = 120,
    speed: float = 1.0,
) -> Path:
    """Write an animated GIF of the cart and the pendulum.

    Parameters
    ----------
    log : mapping of arrays
        The run log (``t, x, phi`` and optionally ``x_ref``, ``force``).
    path : str or Path
        Output GIF.
    params : RobotParams
        For the pendulum length (drawn to scale: shaft + camera) and the track.
    title : str
        Text at the top.
    fps : int
        Target frames per second of the GIF (default 15) (the log is decimated to this rate times
        ``speed``).
    max_frames : int
        Upper bound on the number of frames: a longer run is decimated further (and the GIF
        plays at a lower frame rate, still at ``speed`` times real time).
    speed : float
        Playback speed relative to real time.

    Returns
    -------
    Path
        The file written.
    """
    if fps <= 0 or max_frames <= 0 or speed <= 0:
        raise ValueError("fps, max_frames and speed must be positive")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    t = np.asarray(log["t"], dtype=float)
    x = np.asarray(log["x"], dtype=float)
    phi = np.asarray(log["phi"], dtype=float)
    xr = np.asarray(log["x_ref"], dtype=float) if "x_ref" in log else np.zeros_like(t)
    Ts = float(t[1] - t[0]) if t.size > 1 else 1.0
    step = max(1, int(round(speed / (fps * Ts))), int(math.ceil(t.size / max_frames)))
    idx = np.arange(0, t.size, step)
    length = params.L_shaft + params.L_cam
    cart_w, cart_h = 0.16, 0.06
    lo = min(float(np.min(x)), float(np.min(xr)), 0.0) - length - 0.1
    hi = max(float(np.max(x)), float(np.max(xr)), 0.0) + length + 0.1

    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=70)
    ax.set_xlim(lo, hi)
    ax.set_ylim(-0.08, length + 0.12)
    ax.set_aspect("equal")
    ax.axhline(-cart_h / 2 - 0.012, color="0.3", lw=2)
    track = params.track
    if lo < -track or hi > track:
        for e in (-track, track):
            ax.axvline(e, color="tab:red", lw=1, ls="--")
    cart = Rectangle((x[0] - cart_w / 2, -cart_h / 2), cart_w, cart_h, fc="tab:blue", ec="k")
    ax.add_patch(cart)
    (rod,) = ax.plot([], [], color="0.2", lw=4, solid_capstyle="round")
    (cam,) = ax.plot([], [], "s", color="tab:orange", ms=9, mec="k")
    (ref,) = ax.plot([], [], "v", color="tab:green", ms=8, label="reference")
    txt = ax.text(0.02, 0.95, "", transform=ax.transAxes, va="top", fontsize=9, family="monospace")
    # no tick labels (text dominates the per-frame rendering time): ground marks every 10 cm
    ax.set_axis_off()
    ground = -cart_h / 2 - 0.012
    marks = np.arange(math.floor(lo * 10) / 10, hi + 1e-9, 0.1)
    ax.vlines(marks, ground - 0.015, ground, color="0.3", lw=0.8)
    ax.vlines([0.0], ground - 0.03, ground, color="k", lw=1.5)
    ax.text(0.98, 0.02, "ground marks: 10 cm", transform=ax.transAxes, ha="right", fontsize=7, color="0.3")
    ax.text(0.02, 0.86, title, transform=ax.transAxes, va="top", fontsize=9)

    def draw(i: int):  # noqa: ANN202 - matplotlib artists
        k = idx[i]
        cx, ph = x[k], phi[k]
        cart.set_x(cx - cart_w / 2)
        # phi = deviation from upright, positive in the direction of -x for the report's
        # theta = pi + phi convention: the top leans towards -sin(phi)
        tx, ty = cx - length * math.sin(ph), cart_h / 2 + length * math.cos(ph)
        rod.set_data([cx, tx], [cart_h / 2, ty])
        rod.set_color("tab:red" if abs(ph) >= params.phi_max else "0.2")  # beyond the tilt constraint
        cam.set_data([tx], [ty])
        ref.set_data([xr[k]], [-cart_h / 2 - 0.045])
        txt.set_text(f"t = {t[k]:5.2f} s   phi = {ph:+.3f} rad   x = {cx:+.3f} m")
        return cart, rod, cam, ref, txt

    anim = animation.FuncAnimation(fig, draw, frames=len(idx), blit=False)
    # play in (speed x) real time even when max_frames forced a coarser decimation
    anim.save(str(path), writer=FastPillowWriter(fps=speed / (step * Ts)), dpi=fig.dpi)
    plt.close(fig)
    return path
