"""Motor/drive model and sensor models: sanity, round trips, wrap, noise statistics, batch."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim import motor, sensors
from sim.params import load_params
from sim.sensors import NoiseModel, SensorModel


@pytest.fixture(scope="module")
def p():
    return load_params()


# ---------------------------------------------------------------- motor
def test_stall_force_and_no_load_speed(p) -> None:
    # n*gear*kt*V/(R*r) = 2*10*0.02*12/(2*0.03) = 80 N ; V*r/(kt*gear) = 12*0.03/0.2 = 1.8 m/s
    assert float(motor.stall_force(p)) == pytest.approx(80.0)
    assert float(motor.no_load_speed(p)) == pytest.approx(1.8)
    assert float(motor.force_from_duty(motor.DUTY_MAX, motor.no_load_speed(p), p)) == pytest.approx(0.0, abs=1e-9)
    assert float(motor.force_from_duty(0, 0.0, p)) == 0.0
    # back-EMF: a coasting cart at zero duty is braked, slope = damping
    assert float(motor.force_from_duty(0, 1.0, p)) == pytest.approx(-float(motor.back_emf_damping(p)))


def test_force_is_odd_and_linear_in_duty(p) -> None:
    d = np.array([-32767, -1000, 0, 1000, 32767])
    f = motor.force_from_duty(d, 0.0, p)
    assert np.allclose(f, -f[::-1])
    assert np.allclose(np.diff(f[1:4]), f[3] - f[2])


def test_duty_is_clipped_to_supply(p) -> None:
    assert motor.force_from_duty(10**6, 0.0, p) == pytest.approx(motor.stall_force(p))
    assert motor.duty_from_force(1e4, 0.0, p) == motor.DUTY_MAX
    assert motor.duty_from_force(-1e4, 0.0, p) == -motor.DUTY_MAX


@pytest.mark.parametrize("xdot", [-1.0, 0.0, 0.3, 1.2])
def test_inverse_round_trip(p, xdot: float) -> None:
    forces = np.linspace(-20, 20, 41)
    d = motor.duty_from_force(forces, xdot, p)
    assert d.dtype == np.int64
    back = motor.force_from_duty(d, xdot, p)
    lsb = float(motor.stall_force(p)) / motor.DUTY_MAX
    assert np.max(np.abs(back - forces)) <= 0.5 * lsb + 1e-12


def test_motor_broadcasts_over_batch_and_parameter_arrays(p) -> None:
    duty = np.array([1000, 2000, 3000])
    xd = np.array([0.0, 0.1, 0.2])
    f = motor.force_from_duty(duty, xd, p)
    assert f.shape == (3,)
    mp = {k: getattr(p, k) for k in motor.MOTOR_KEYS}
    mp["kt"] = np.array([0.02, 0.02, 0.03])
    f2 = motor.force_from_duty(duty, xd, mp)
    assert f2[:2] == pytest.approx(f[:2]) and f2[2] != pytest.approx(f[2])
    lo, hi = motor.force_limits(np.zeros((2, 5)), p)
    assert lo.shape == hi.shape == (2, 5)
    with pytest.raises(KeyError, match="kt"):
        motor.force_from_duty(1, 0.0, {"V_supply": 12})


# ---------------------------------------------------------------- sensors
def test_adc_round_trip_and_clip(p) -> None:
    q = p.pot_range / 2**p.adc_bits
    phi = np.linspace(-0.5, 0.5, 1001)
    adc = sensors.phi_to_adc(phi, p)
    assert adc.dtype == np.int64
    assert np.max(np.abs(sensors.adc_to_phi(adc, p) - phi)) <= q / 2 + 1e-12
    assert int(sensors.phi_to_adc(0.0, p)) == p.pot_offset
    assert int(sensors.phi_to_adc(10.0, p)) == 2**p.adc_bits - 1
    assert int(sensors.phi_to_adc(-10.0, p)) == 0


def test_encoder_round_trip_and_wrap(p) -> None:
    cpm = sensors.enc_counts_per_m(p)
    assert cpm == pytest.approx(1200 / (2 * math.pi * 0.03))
    x = np.linspace(-1.0, 1.0, 777)
    enc = sensors.x_to_encoder(x, p)
    assert enc.min() >= 0 and enc.max() <= 65535
    assert np.max(np.abs(sensors.encoder_to_x(enc, p) - x)) <= 0.5 / cpm + 1e-12
    # negative positions wrap to the top of the counter
    assert int(sensors.x_to_encoder(-1.0 / cpm, p)) == 65535
    # deltas across the wrap
    assert int(sensors.encoder_delta(2, 65534)) == 4
    assert int(sensors.encoder_delta(65534, 2)) == -4


def test_unwrapper_follows_long_travel(p) -> None:
    cpm = sensors.enc_counts_per_m(p)
    x = np.linspace(0, 25.0, 5001)  # 25 m: ~160k counts, many wraps
    enc = sensors.x_to_encoder(x, p)
    u = sensors.EncoderUnwrapper(enc[0])
    tot = np.array([u.update(c) for c in enc])
    assert np.max(np.abs(tot / cpm - x)) <= 0.5 / cpm + 1e-9


def test_delay_line(p) -> None:
    s = SensorModel(p, delay=0.01)
    assert s.delay_steps == 5
    s.reset(0.0, 0.0)
    outs = [s.measure(0.0, phi)[0] for phi in np.arange(1, 11) * 0.01]
    assert all(int(o) == p.pot_offset for o in outs[:5])
    assert [int(o) for o in outs[5:]] == [int(sensors.phi_to_adc(v, p)) for v in np.arange(1, 6) * 0.01]
    s0 = SensorModel(p, delay=0.0)
    assert int(s0.measure(0.0, 0.1)[0]) == int(sensors.phi_to_adc(0.1, p))


def test_white_noise_variance_is_power_over_sample_time(p) -> None:
    m = NoiseModel(kind="white", power=1e-5)
    Ts = 1 / p.rate
    assert m.variance(Ts) == pytest.approx(1e-5 * 500)
    src = sensors.NoiseSource(m, Ts, np.random.default_rng(1), batch_shape=(4000,))
    d = np.concatenate([src.draw() for _ in range(10)], axis=1)
    assert d.shape == (2, 40000)
    assert np.var(d[1]) == pytest.approx(5e-3, rel=0.05)
    held = NoiseModel(kind="white", power=1e-5, sample_time=0.01)
    assert held.variance(Ts) == pytest.approx(1e-3) and held.hold_ticks(Ts) == 5
    src = sensors.NoiseSource(held, Ts, np.random.default_rng(1))
    seq = np.array([src.draw()[1] for _ in range(10)])
    assert np.all(seq[:5] == seq[0]) and np.all(seq[5:] == seq[5]) and seq[0] != seq[5]


def test_uniform_noise_and_channels(p) -> None:
    m = NoiseModel(kind="uniform", amplitude=0.005, channels=("phi",))
    src = sensors.NoiseSource(m, 0.002, np.random.default_rng(2), batch_shape=(20000,))
    d = src.draw()
    assert np.all(d[0] == 0.0)
    assert np.max(np.abs(d[1])) <= 0.005 and np.max(np.abs(d[1])) > 0.0049
    assert np.var(d[1]) == pytest.approx(0.005**2 / 3, rel=0.05)
    with pytest.raises(ValueError, match="kind"):
        NoiseModel(kind="pink")
    with pytest.raises(ValueError, match="channels"):
        NoiseModel(kind="white", power=1.0, channels=("theta",))


def test_sensor_model_is_seeded_and_batched(p) -> None:
    def run(seed: int) -> np.ndarray:
        s = SensorModel(p, noise=NoiseModel(kind="white", power=1e-5), rng=seed, batch_shape=(3,))
        return np.array([s.measure(np.zeros(3), np.zeros(3))[0] for _ in range(20)])

    a, b, c = run(7), run(7), run(8)
    assert a.shape == (20, 3)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.all(a[:5] == p.pot_offset) and np.std(a[5:]) > 10  # ~61 counts rms after the delay
