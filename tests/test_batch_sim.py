"""The batch closed-loop simulator: agreement with the per-run python-control loop, run by run."""

from __future__ import annotations

import numpy as np
import pytest

from host.design.discrete import controller_ss
from sim.batch import (
    BatchError,
    RunSet,
    closed_loop_iosys,
    draw_noise,
    estimator_rows,
    simulate_batch,
    simulate_run,
)
from sim.params import load_params
from sim.sensors import NoiseModel, NoiseSource

STATES = ("x", "xdot", "phi", "phidot")


@pytest.fixture(scope="module")
def p():
    return load_params()


@pytest.fixture(scope="module")
def ctrl(p):
    return controller_ss(p)


def _runs(p, n: int = 5) -> RunSet:
    # every run different: robot, delay (incl. 0 and the longest), seed, tilt, reference
    f = np.linspace(0.9, 1.1, n)
    x0 = np.zeros((n, 4))
    x0[:, 2] = np.linspace(-0.04, 0.05, n)
    x0[:, 1] = np.linspace(0.0, 0.1, n)
    return RunSet(
        x0=x0,
        values={"M": p.M * f, "m": p.m * f[::-1], "L": p.L * np.sqrt(f), "I": p.I * f**2, "b": p.b * 2 * f,
                "R": p.R * f[::-1], "kt": p.kt * f},
        delay_ticks=np.array([0, 2, 5, 7, 10][:n]),
        noise_seed=np.arange(n) * 7919 + 11,
        x_ref=np.linspace(0.0, 0.02, n),
    )


@pytest.mark.parametrize(
    "noise,drive",
    [(NoiseModel("uniform", amplitude=0.003), "motor"), (NoiseModel("white", power=2e-9), "force")],
    ids=["uniform-motor", "white-force"],
)
def test_batch_agrees_with_python_control_run_by_run(p, ctrl, noise, drive) -> None:
    runs = _runs(p)
    res = simulate_batch(p, ctrl, runs, duration=1.0, noise=noise, drive=drive, record=True)
    tr = res.traces
    assert tr is not None and tr["phi"].shape == (501, len(runs))
    for i in range(len(runs)):
        ref = simulate_run(p, ctrl, runs, i, duration=1.0, noise=noise, drive=drive)
        for k in STATES:
            np.testing.assert_allclose(tr[k][:, i], ref[k], rtol=0, atol=1e-9, err_msg=f"run {i} {k}")
    # the runs really differ from one another (per-run parameters, delays, seeds are used)
    assert np.ptp(tr["phi"][-1]) > 1e-4
    assert np.all(np.ptp(tr["phi"], axis=0) > 1e-3)


def test_reference_detects_a_wrong_parameter(p, ctrl) -> None:
    # the comparison above can fail: the same run with another cart mass differs clearly
    runs = _runs(p, 2)
    other = RunSet(x0=runs.x0, values={**runs.values, "M": runs.values["M"] * 1.2}, delay_ticks=runs.delay_ticks,
                   noise_seed=runs.noise_seed, x_ref=runs.x_ref)
    a = simulate_batch(p, ctrl, runs, duration=1.0, record=True).traces
    b = simulate_run(p, ctrl, other, 1, duration=1.0)
    assert np.max(np.abs(a["phi"][:, 1] - b["phi"])) > 1e-4


def test_result_of_a_run_does_not_depend_on_its_batch(p, ctrl) -> None:
    runs = _runs(p)
    noise = NoiseModel("uniform", amplitude=0.002)
    full = simulate_batch(p, ctrl, runs, duration=0.6, noise=noise).metrics
    for idx in (slice(0, 2), slice(2, 5), np.array([4, 1])):
        part = simulate_batch(p, ctrl, runs.subset(idx), duration=0.6, noise=noise).metrics
        for k, v in part.items():
            assert np.array_equal(v, full[k][idx]), k


def test_noise_streams_match_a_single_run_noise_source(p) -> None:
    for model in (NoiseModel("white", power=1e-6, sample_time=0.006), NoiseModel("uniform", amplitude=0.01, channels=("phi",))):
        seeds = np.array([3, 99])
        got = draw_noise(model, 0.002, seeds, 0, 40)
        for i, s in enumerate(seeds):
            src = NoiseSource(model, 0.002, np.random.default_rng(int(s)))
            want = np.stack([src.draw().copy() for _ in range(40)])
            assert np.array_equal(got[:, :, i], want)


def test_estimator_rows_equal_the_controller_estimate(p, ctrl) -> None:
    ce, de = estimator_rows(ctrl)
    rng = np.random.default_rng(0)
    for _ in range(5):
        z, v = rng.standard_normal(ctrl.n), rng.standard_normal(3)
        assert ce @ z + de @ v == pytest.approx(ctrl.estimate(z, v)[1], rel=1e-12, abs=1e-12)


def test_metrics_are_consistent_with_the_traces(p, ctrl) -> None:
    runs = _runs(p, 3)
    res = simulate_batch(p, ctrl, runs, duration=2.0, noise=NoiseModel("uniform", amplitude=0.001), record=True)
    m, tr = res.metrics, res.traces
    # the metrics look at every RK4 sub-step, the traces at ticks: never less
    assert np.all(m["phi_max"] >= np.max(np.abs(tr["phi"]), axis=0))
    assert np.all(m["force_max"] >= np.max(np.abs(tr["force"]), axis=0) - 1e-12)
    settled = np.isfinite(m["settle"])
    assert settled[:2].all()
    after = tr["t"][:, None] >= m["settle"][None, :]
    assert np.all(np.abs(tr["phi"])[after] <= 0.005)
    # a settled run was out of the band shortly before settling
    for i in np.flatnonzero(settled & (m["settle"] > 0)):
        k = int(np.searchsorted(tr["t"], m["settle"][i]))
        assert np.max(np.abs(tr["phi"][: k + 1, i])) > 0.02
    assert not m["fallen"].any()


def test_accel_limit_holds(p) -> None:
    c = controller_ss(p, u_max=(p.M + p.m) * p.a_max)
    x0 = np.zeros((3, 4))
    x0[:, 2] = [0.02, 0.1, 0.2]
    runs = RunSet(x0=x0, delay_ticks=np.full(3, 5))
    free = simulate_batch(p, c, runs, duration=0.5).metrics
    lim = simulate_batch(p, c, runs, duration=0.5, accel_limit=p.a_max).metrics
    assert free["xddot_max"].max() > p.a_max  # the limit matters here ...
    assert lim["xddot_max"].max() <= p.a_max + 1e-9  # ... and holds


def test_a_fallen_pendulum_is_flagged_and_never_settles(p, ctrl) -> None:
    runs = RunSet(x0=np.array([[0, 0, 0.01, 0], [0, 0, 1.2, 0]]), delay_ticks=np.array([5, 5]))
    m = simulate_batch(p, controller_ss(p, u_max=1.0), runs, duration=1.5).metrics
    assert list(m["fallen"]) == [False, True]
    assert np.isinf(m["settle"][1])


def test_bad_inputs_are_rejected(p, ctrl) -> None:
    with pytest.raises(BatchError, match="cannot vary"):
        RunSet(x0=np.zeros((2, 4)), values={"rate": [1, 2]})
    with pytest.raises(BatchError, match="shape"):
        RunSet(x0=np.zeros((2, 3)))
    with pytest.raises(BatchError, match="delay_ticks"):
        RunSet(x0=np.zeros((2, 4)), delay_ticks=np.array([1, -1]))
    with pytest.raises(BatchError, match="positive"):
        RunSet(x0=np.zeros((2, 4)), values={"M": [0.5, -0.5]})
    runs = RunSet(x0=np.zeros((1, 4)))
    with pytest.raises(BatchError, match="drive"):
        simulate_batch(p, ctrl, runs, drive="jet")
    with pytest.raises(BatchError, match="duration"):
        simulate_batch(p, ctrl, runs, duration=0.0)
    with pytest.raises(BatchError, match="drive"):
        closed_loop_iosys(p, ctrl, runs.true_params(p, 0), 0, drive="jet")


def test_shape_errors_are_batch_errors() -> None:
    with pytest.raises(BatchError, match="3 numbers"):
        RunSet(x0=np.zeros((3, 4)), values={"M": [0.5, 0.6]})
    with pytest.raises(BatchError, match="x_ref"):
        RunSet(x0=np.zeros((3, 4)), x_ref=[0.0, 0.1])
    with pytest.raises(BatchError, match="finite"):
        RunSet(x0=np.array([[0.0, 0.0, np.nan, 0.0]]))


def test_several_controllers_in_one_batch(p, ctrl) -> None:
    soft = controller_ss(p, R=0.1, u_max=4.0)
    runs = _runs(p, 4)
    idx = np.array([1, 0, 1, 0])
    noise = NoiseModel("uniform", amplitude=0.002)
    both = simulate_batch(p, [ctrl, soft], runs, ctrl_index=idx, noise=noise, duration=0.6).metrics
    for c, k in ((ctrl, 0), (soft, 1)):
        alone = simulate_batch(p, c, runs.subset(idx == k), noise=noise, duration=0.6).metrics
        for name in ("phi_max", "force_max", "xddot_max", "phi_rms"):
            np.testing.assert_allclose(both[name][idx == k], alone[name], rtol=1e-12, atol=1e-15)
    # the designs really differ: the soft runs would have asked for more force from the other
    hard = simulate_batch(p, ctrl, runs.subset(idx == 1), noise=noise, duration=0.6).metrics
    assert np.all(hard["force_max"] > both["force_max"][idx == 1])
    with pytest.raises(BatchError, match="ctrl_index"):
        simulate_batch(p, [ctrl, soft], runs, ctrl_index=np.array([0, 1, 2, 0]), duration=0.1)
    with pytest.raises(BatchError, match="ctrl_index"):
        simulate_batch(p, ctrl, runs, ctrl_index=idx, duration=0.1)
    with pytest.raises(BatchError, match="same number of states"):
        simulate_batch(p, [ctrl, controller_ss(p, delay=0.004)], runs, ctrl_index=idx, duration=0.1)
