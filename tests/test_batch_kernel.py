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
