"""PNG and GIF outputs are written, non-trivial, and the GIF is decimated and timed."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from sim.metrics import evaluate
from sim.params import load_params
from sim.plantsim import PlantSim
from sim.plots import animate_run, plot_run
from sim.scenario import load_scenario


@pytest.fixture(scope="module")
def run():
    p = load_params()
    sc = load_scenario("square_wave_20cm_2p2s")
    sim = PlantSim(p, sc)
    # a crude stabiliser on the true state is enough to get moving signals
    while sim.tick < 1500:
        x = sim.state
        u = 73.5 * (x[0] - sim.x_ref()) + 43.6 * x[1] - 133.3 * x[2] - 28.8 * x[3]
        sim.step(int(np.clip(u / 80.0 * 32767, -32767, 32767)))
    return p, sc, sim.result()


def test_png_is_written(tmp_path, run) -> None:
    p, sc, log = run
    m = evaluate(log, sc, p).metrics
    out = plot_run(log, tmp_path / "sub" / "run.png", p, title="t", metrics=m,
                   overlay={"shifted": {k: (v + 0.01 if k in ("phi", "x") else v) for k, v in log.items()}})
    assert out.exists() and out.stat().st_size > 20_000
    with Image.open(out) as im:
        assert im.format == "PNG" and im.size[0] > 600 and im.size[1] > 600


def test_gif_is_written_decimated_and_real_time(tmp_path, run) -> None:
    p, _, log = run
    out = animate_run(log, tmp_path / "run.gif", p, title="t", fps=20, max_frames=40)
    assert out.stat().st_size > 10_000
    with Image.open(out) as im:
        assert im.format == "GIF" and im.n_frames == 40
        durations = []
        for i in range(im.n_frames):
            im.seek(i)
            durations.append(im.info["duration"])
        frames = [np.asarray(im.convert("RGB")) for _ in [im.seek(0)]] + [np.asarray((im.seek(39), im.convert("RGB"))[1])]
    # 1500 ticks = 3 s in 40 frames: each frame ~75 ms, total ~ real time
    assert sum(durations) == pytest.approx(3000, rel=0.1)
    assert not np.array_equal(frames[0], frames[1])  # something moves


def test_gif_bad_arguments(tmp_path, run) -> None:
    p, _, log = run
    with pytest.raises(ValueError, match="positive"):
        animate_run(log, tmp_path / "x.gif", p, fps=0)
