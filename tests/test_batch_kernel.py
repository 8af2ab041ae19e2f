"""The compiled batch kernel is bit-identical to the numpy reference, run by run (issue 15 item 6).

Hundreds of runs with measurement delay (0..10 ticks), ADC/encoder quantisation, noise
(uniform; white held over several ticks), force saturation and the cart-acceleration clip,
falling runs included: every metric and every trace ``array_equal``.
"""

from __future__ import annotations

import numpy as np
import pytest

from host.design.discrete import controller_ss
from sim import batch_kernel
from sim.batch import BatchError, RunSet, default_engine, simulate_batch
from sim.params import load_params
from sim.sensors import NoiseModel

pytestmark = pytest.mark.skipif(not batch_kernel.AVAILABLE, reason="numba not installed")


@pytest.fixture(scope="module")
def p():
    return load_params()


def _runs(p, n: int, seed: int = 1) -> RunSet:
    rng = np.random.default_rng(seed)
    f = rng.uniform(0.7, 1.3, (n, 8))
    x0 = np.zeros((n, 4))
    x0[:, 2] = rng.uniform(-0.35, 0.35, n)  # some of them fall
    x0[:, 1] = rng.uniform(-0.1, 0.1, n)
    return RunSet(x0=x0, values={"M": p.M * f[:, 0], "m": p.m * f[:, 1], "I": p.I * f[:, 2], "b": p.b * f[:, 3],
                                 "R": p.R * f[:, 4], "kt": p.kt * f[:, 5], "V_supply": p.V_supply * f[:, 6]},
                  delay_ticks=rng.integers(0, 11, n), noise_seed=rng.integers(0, 2**62, n),
                  x_ref=rng.uniform(-0.05, 0.05, n))


def _same(a, b) -> None:
    for k in a.metrics:
        assert np.array_equal(a.metrics[k], b.metrics[k]), k
    if a.traces is not None:
        assert set(a.traces) == set(b.traces)
        for k in a.traces:
            assert np.array_equal(a.traces[k], b.traces[k]), k


def test_numpy_trig_is_libm_here() -> None:
    # the condition for bit-identity (see sim.batch_kernel); true on x86-64 without AVX-512
    assert batch_kernel.numpy_trig_is_libm()


@pytest.mark.parametrize("noise, accel, u_max, drive", [
    (NoiseModel("uniform", amplitude=0.003), None, None, "motor"),
    (NoiseModel("white", power=2e-9, sample_time=0.006), 5.0, None, "motor"),
    (NoiseModel("uniform", amplitude=0.001, channels=("phi",)), None, 0.8, "motor"),
    (NoiseModel(), 4.4, 1.5, "force"),
], ids=["uniform", "white-held-accel-clip", "phi-only-saturated", "force-drive"])
def test_kernel_is_bit_identical_to_numpy(p, noise, accel, u_max, drive) -> None:
    runs = _runs(p, 150)
    ctrl = controller_ss(p, u_max=u_max) if u_max is not None else controller_ss(p)
    kw = dict(duration=0.8, noise=noise, accel_limit=accel, drive=drive, record=True)
    a = simulate_batch(p, ctrl, runs, engine="numpy", **kw)
    b = simulate_batch(p, ctrl, runs, engine="numba", **kw)
    _same(a, b)
    assert 0 < int(np.sum(a.metrics["fallen"])) < len(runs) or drive == "force"
    if u_max is not None:
        assert np.max(np.abs(a.traces["u_sat"])) == u_max  # saturated


def test_kernel_bit_identical_with_stacked_designs_and_a_plant(p) -> None:
    runs = _runs(p, 120, seed=2)
    plant = p.replace(I=0.7 * p.I, pot_offset=p.pot_offset + 3, r_wheel=p.r_wheel * 1.02)
    ctrls = [controller_ss(p), controller_ss(p, u_max=1.0)]
    idx = np.arange(len(runs)) % 2
    kw = dict(duration=0.6, noise=NoiseModel("uniform", amplitude=0.002), ctrl_index=idx, plant=plant, record=True)
    _same(simulate_batch(p, ctrls, runs, engine="numpy", **kw), simulate_batch(p, ctrls, runs, engine="numba", **kw))
    # and the plant matters
    m0 = simulate_batch(p, ctrls, runs, engine="numba", duration=0.6, ctrl_index=idx).metrics
    m1 = simulate_batch(p, ctrls, runs, engine="numba", duration=0.6, ctrl_index=idx, plant=plant).metrics
    assert not np.array_equal(m0["phi_max"], m1["phi_max"])


def test_kernel_bit_identical_with_the_supply_measured(p) -> None:
    # the firmware inverts the motor with each run's measured (true) supply: supply_measured
    runs = _runs(p, 100, seed=4)
    kw = dict(duration=0.6, noise=NoiseModel("uniform", amplitude=0.002), record=True, supply_measured=True)
    a = simulate_batch(p, controller_ss(p), runs, engine="numpy", **kw)
    _same(a, simulate_batch(p, controller_ss(p), runs, engine="numba", **kw))
    # and it is what it says: the duty is V / V_true, not V / V_nominal
    b = simulate_batch(p, controller_ss(p), runs, engine="numba", **{**kw, "supply_measured": False})
    assert not np.array_equal(a.traces["duty"], b.traces["duty"])
    ratio = runs.values["V_supply"] / p.V_supply
    k = np.argmax(np.abs(ratio - 1.0))  # the run whose supply is furthest from nominal
    t = 0  # the first tick: same state, same command in both
    assert a.traces["duty"][t, k] == pytest.approx(b.traces["duty"][t, k] / ratio[k], abs=1.0)


def test_a_run_does_not_depend_on_its_chunk(p, monkeypatch) -> None:
    import sim.batch

    runs = _runs(p, 37, seed=3)
    ctrl = controller_ss(p)
    kw = dict(duration=0.4, noise=NoiseModel("white", power=1e-9))
    whole = simulate_batch(p, ctrl, runs, engine="numba", **kw)
    monkeypatch.setattr(sim.batch, "KERNEL_CHUNK", 5)
    _same(whole, simulate_batch(p, ctrl, runs, engine="numba", **kw))


def test_engine_option(p) -> None:
    assert default_engine() == "numba"
    with pytest.raises(BatchError, match="engine"):
        simulate_batch(p, controller_ss(p), _runs(p, 2), engine="fortran")


@pytest.mark.slow
def test_kernel_trig_is_numpys_on_a_large_sample() -> None:
    # the kernel's sine and cosine of one angle compile to one glibc sincos call: bit for bit
    # numpy's np.sin/np.cos on 10 x 1e6 values from 1e-9 to 1e9 rad
    assert batch_kernel.kernel_trig_is_numpys(n=1_000_000)


def test_rms_window_inside_the_run(p) -> None:
    # runs longer than the RMS window: phi_rms/force_rms sum only the window's samples
    runs = _runs(p, 40, seed=4)
    kw = dict(duration=1.2, window=0.5, noise=NoiseModel("uniform", amplitude=0.002))
    a = simulate_batch(p, controller_ss(p), runs, engine="numpy", **kw)
    b = simulate_batch(p, controller_ss(p), runs, engine="numba", **kw)
    _same(a, b)
    whole = simulate_batch(p, controller_ss(p), runs, engine="numba", **{**kw, "window": 1.2})
    assert not np.array_equal(whole.metrics["phi_rms"], b.metrics["phi_rms"])


@pytest.mark.parametrize("noise", [NoiseModel("uniform", amplitude=0.003),
                                   NoiseModel("white", power=2e-9, sample_time=0.006)], ids=["uniform", "white-held"])
def test_noise_drawn_in_the_kernel_or_beforehand(p, noise, monkeypatch) -> None:
    # in the kernel, each run's generator through numpy's C draw functions; without them,
    # drawn beforehand into an array: the same numbers either way, the reference's
    assert batch_kernel.draw_functions() is not None
    runs = _runs(p, 37, seed=5)
    kw = dict(duration=0.5, noise=noise, record=True)
    ref = simulate_batch(p, controller_ss(p), runs, engine="numpy", **kw)
    _same(ref, simulate_batch(p, controller_ss(p), runs, engine="numba", **kw))
    monkeypatch.setattr(batch_kernel, "draw_functions", lambda: None)
    _same(ref, simulate_batch(p, controller_ss(p), runs, engine="numba", **kw))


def test_draw_functions_draw_what_the_generator_draws() -> None:
    import ctypes

    fns = batch_kernel.draw_functions()
    assert fns is not None and set(fns) == {"uniform", "white"}
    for kind, addr in fns.items():
        call = ctypes.CFUNCTYPE(ctypes.c_double, ctypes.c_void_p)(addr)
        ref_gen, gen = np.random.default_rng(99), np.random.default_rng(99)
        ref = ref_gen.random(5000) if kind == "uniform" else ref_gen.standard_normal(5000)
        state = batch_kernel.bitgen_address(gen)
        assert np.array_equal(ref, [call(state) for _ in range(5000)]), kind


@pytest.mark.parametrize("n, threads, in_memory", [(10_000, 2, False), (10_000, 8, False), (150, 2, False),
                                                    (7, 1, False), (10_000, 2, True), (1, 4, True)])
def test_kernel_chunk_is_sized_to_the_workers(n, threads, in_memory) -> None:
    from sim.batch import kernel_chunk

    lanes = batch_kernel.LANES
    c = kernel_chunk(n, threads, lanes, in_memory)
    assert 1 <= c <= n
    calls = -(-n // c)
    assert c == n or c % lanes == 0  # whole lane groups: only the batch's last group is short
    if c < n:
        assert c >= lanes * threads * 8  # every thread gets several groups per call
    if in_memory:
        assert c <= max(2048, lanes * threads * 8)  # the noise array of a call stays bounded
    else:
        assert calls <= 4
