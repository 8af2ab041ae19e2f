"""Sensor models: what the board's hardware reads, with quantisation, noise and delay.

Angle potentiometer -> 12-bit ADC (the agreed interface)::

    adc = clip(round(pot_offset + (phi + n_phi) * 2**adc_bits / pot_range), 0, 2**adc_bits - 1)

with the potentiometer's integral nonlinearity (plant realism, ``sensors.pot_inl``, default 0)
added to the ideal count ``c = pot_offset + (phi + n_phi) * 2**adc_bits / pot_range`` before the
rounding::

    c' = c + pot_inl * 2**adc_bits * sin(2*pi * pot_inl_cycles * c / 2**adc_bits)

(a sine over the wiper's position on the track, in fractions of the full scale; ``pot_inl_cycles``
= 0.5 is a bow, zero at both ends; 1 an S, the classic pot linearity error).  The firmware decodes
the counts as if the pot were linear.  With the motor encoder on the motor shaft, the encoder
reads the motor side of the gear play (``sim.plantsim``, ``sim.batch``): the caller passes that
position as ``x``.

Cart encoder -> quadrature counts in a 16-bit hardware counter::

    enc = round((x + n_x) / (2*pi*r_wheel) * enc_cpr)  mod 65536

The noise is added to the physical quantity (rad, m) *before* quantisation, so a noise
smaller than half a count can vanish in the rounding, as on the real ADC.

Measurement delay: every reading reaches the controller ``delay_steps = round(delay * rate)``
control ticks after it was taken (10 ms at 500 Hz = 5 ticks).  The delay line starts filled
with the reading of the initial state (the sensors have been reading the resting robot).

Noise models (:class:`NoiseModel`)
----------------------------------
``white``
    Simulink's *Band-Limited White Noise* block.  Its "noise power" ``P`` is the height of
    the power spectral density of the continuous white noise being approximated, in
    (unit)^2 * s, i.e. rad^2/Hz for the angle and m^2/Hz for the cart position.  Sampled with
    a correlation time (sample time) ``Ts`` the block outputs independent Gaussian samples of
    **variance P / Ts** (standard deviation ``sqrt(P/Ts)``), each held for ``Ts``.  The report's
    "white noise of power 0.00001" therefore means, at the 500 Hz loop (Ts = 2 ms), a sample
    variance of 1e-5 / 2e-3 = 5e-3 rad^2, a standard deviation of 0.0707 rad (4.1 deg) on the
    angle -- the same order as the report's observed +-4.5 deg oscillation.  ``sample_time``
    defaults to the control period; a longer one holds each sample for that many ticks (and
    lowers the variance accordingly, as the Simulink block does).  The report does not give
    its block's sample time; the block's default is 0.1 s, with which the same power would
    mean 0.01 rad rms held for 0.1 s -- ``sample_time = 0.1`` in a scenario reproduces that
    reading.  (Modelica's ``BandLimitedWhiteNoise`` uses the same rule:
    ``sigma = sqrt(noisePower / samplePeriod)``.)
``uniform``
    Independent samples uniform in ``[-amplitude, +amplitude]`` each tick (the report's
    "uniform random noise between -0.005 and 0.005"), variance ``amplitude**2 / 3``.
``none``
    No noise.

The report adds the noise "on both outputs" (angle and cart position), so both channels are
noisy by default; ``channels`` restricts it.  All randomness comes from a seeded
:class:`numpy.random.Generator`.

Every function broadcasts over a batch: pass arrays of shape ``(N,)`` (or any shape) and
build :class:`SensorModel` with ``batch_shape=(N,)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Union

import numpy as np

from .params import SCHEMA, RobotParams

__all__ = [
    "ENC_MODULUS",
    "CHANNELS",
    "adc_counts_per_rad",
    "enc_counts_per_m",
    "phi_to_adc",
    "adc_to_phi",
    "x_to_encoder",
    "encoder_to_x",
    "encoder_delta",
    "inl_terms",
    "EncoderUnwrapper",
    "delay_steps",
    "NoiseModel",
    "NoiseSource",
    "DelayLine",
    "SensorModel",
]

ENC_MODULUS = 1 << 16
"""The encoder counter wraps modulo 65536 (0..65535)."""

CHANNELS = ("x", "phi")
"""Measured channels, in the order of every ``(2, ...)`` array here: cart position, angle."""

ParamsLike = Union[RobotParams, Mapping[str, "float | np.ndarray"]]


_DOTTED = {k.split(".", 1)[1]: k for k in SCHEMA}


_OPTIONAL = {"pot_inl": 0.0, "pot_inl_cycles": 1.0}  # realism keys a mapping may leave out


def _get(params: ParamsLike, key: str):  # noqa: ANN202 - float or ndarray
    # direct dotted lookup for RobotParams (its __getattr__ scans every key)
    if isinstance(params, RobotParams):
        return params.values[_DOTTED[key]]
    return params[key] if key in params or key not in _OPTIONAL else _OPTIONAL[key]


def inl_terms(params: ParamsLike) -> tuple[float | np.ndarray, float | np.ndarray]:
    """``(amplitude in counts, angular rate in rad per count)`` of the pot's nonlinearity:
    ``pot_inl * 2**adc_bits`` and ``2*pi * pot_inl_cycles / 2**adc_bits``."""
    full = 2.0 ** _get(params, "adc_bits")
    return _get(params, "pot_inl") * full, 2.0 * math.pi * _get(params, "pot_inl_cycles") / full


def adc_counts_per_rad(params: ParamsLike) -> float | np.ndarray:
    """ADC counts per radian of tilt, ``2**adc_bits / pot_range``."""
    return 2.0 ** _get(params, "adc_bits") / _get(params, "pot_range")


def pot_gain_at_upright(params: ParamsLike) -> float | np.ndarray:
    """The pot's slope at the upright reading over its nominal one (:func:`adc_counts_per_rad`):
    ``1 + amp w cos(w pot_offset)`` with the nonlinearity's sine (``pot_inl``; 1 without it)."""
    amp, w = inl_terms(params)
    return 1.0 + amp * w * np.cos(w * _get(params, "pot_offset"))


def enc_counts_per_m(params: ParamsLike) -> float | np.ndarray:
    """Encoder counts per metre of cart travel, ``enc_cpr / (2*pi*r_wheel)``."""
    return _get(params, "enc_cpr") / (2.0 * math.pi * _get(params, "r_wheel"))


def phi_to_adc(phi: np.ndarray | float, params: ParamsLike, noise: np.ndarray | float = 0.0) -> np.ndarray:
    """ADC counts the potentiometer gives at tilt ``phi`` (rad), plus ``noise`` (rad).

    Returns
    -------
    ndarray of int64
        ``clip(round(pot_offset + (phi + noise) * 2**adc_bits / pot_range), 0, 2**adc_bits - 1)``,
        with the pot's nonlinearity (``pot_inl``) added before the rounding.
    """
    full = 2 ** np.asarray(_get(params, "adc_bits"), dtype=np.int64)
    lin = _get(params, "pot_offset") + (np.asarray(phi, dtype=float) + noise) * adc_counts_per_rad(params)
    amp, w = inl_terms(params)
    if np.any(np.asarray(amp) != 0):
        lin = np.where(np.asarray(amp) != 0, lin + amp * np.sin(w * lin), lin)
    return np.clip(np.rint(lin), 0, full - 1).astype(np.int64)


def adc_to_phi(adc: np.ndarray | int, params: ParamsLike) -> np.ndarray:
    """Tilt (rad) from ADC counts: ``(adc - pot_offset) * pot_range / 2**adc_bits``."""
    return (np.asarray(adc, dtype=float) - _get(params, "pot_offset")) / adc_counts_per_rad(params)


def x_to_encoder(x: np.ndarray | float, params: ParamsLike, noise: np.ndarray | float = 0.0) -> np.ndarray:
    """16-bit encoder counter value at cart position ``x`` (m), plus ``noise`` (m).

    Returns
    -------
    ndarray of int64
        ``round((x + noise) * enc_cpr / (2*pi*r_wheel)) mod 65536``, in ``0..65535``.
    """
    counts = np.rint((np.asarray(x, dtype=float) + noise) * enc_counts_per_m(params)).astype(np.int64)
    return np.mod(counts, ENC_MODULUS)


def encoder_delta(new: np.ndarray | int, old: np.ndarray | int) -> np.ndarray:
    """Signed count difference ``new - old`` across the 16-bit wrap, in ``-32768..32767``."""
    d = (np.asarray(new, dtype=np.int64) - np.asarray(old, dtype=np.int64)) % ENC_MODULUS
    return np.where(d >= ENC_MODULUS // 2, d - ENC_MODULUS, d)


def encoder_to_x(count: np.ndarray | int, params: ParamsLike) -> np.ndarray:
    """Cart position (m) from one counter value, read as a signed 16-bit number.

    Valid while ``|x|`` is below half the counter range (32768 counts, 5.1 m with the default
    wheel and encoder); use :class:`EncoderUnwrapper` to follow longer travel.
    """
    return encoder_delta(count, 0) / enc_counts_per_m(params)


class EncoderUnwrapper:
    """Follows the 16-bit counter across wraps, like the firmware does.

    Parameters
    ----------
    first : int or array_like
        The first counter value (defines position 0 of the unwrapped count unless
        ``origin`` is given).
    origin : int or array_like, optional
        Counter value that corresponds to ``x = 0`` (default 0: the counter was zeroed at
        ``x = 0``).

    Notes
    -----
    Correct while successive readings differ by less than 32768 counts.
    """

    def __init__(self, first: np.ndarray | int, origin: np.ndarray | int = 0) -> None:
        self._last = np.asarray(first, dtype=np.int64).copy()
        self.total = encoder_delta(first, origin).astype(np.int64)

    def update(self, count: np.ndarray | int) -> np.ndarray:
        """Feed a new counter value; return the unwrapped count (int64)."""
        self.total = self.total + encoder_delta(count, self._last)
        self._last = np.asarray(count, dtype=np.int64).copy()
        return self.total


DELAY_TICK_TOL = 1e-6
"""How far from a whole number of ticks a delay may be (float noise of ``delay * rate``)."""


def delay_steps(delay: float, rate: float) -> int:
    """Measurement delay in whole control ticks, ``delay * rate``.

    The sensors are sampled once per control tick, so the simulated delay line holds whole
    ticks: a delay that is not a whole number of ticks (beyond :data:`DELAY_TICK_TOL`) is
    refused, never rounded.

    Raises
    ------
    ValueError
        A negative delay, a rate <= 0, or a delay that is not a whole number of ticks.
    """
    if not (delay >= 0 and rate > 0):
        raise ValueError(f"delay must be >= 0 and rate > 0, got delay={delay!r}, rate={rate!r}")
    ticks = delay * rate
    n = round(ticks)
    if abs(ticks - n) > DELAY_TICK_TOL:
        raise ValueError(f"delay {delay!r} s is {ticks:.6g} ticks at {rate:g} Hz: not a whole number of sensor "
                         f"samples ({1e3 / rate:g} ms each); the simulator does not round it")
    return int(n)


@dataclass(frozen=True)
class NoiseModel:
    """Measurement noise on the sensor channels (see the module docstring).

    Parameters
    ----------
    kind : {"none", "white", "uniform"}
        Noise model.
    power : float
        ``white``: noise power (PSD height) in unit^2 * s (rad^2/Hz, m^2/Hz).
    amplitude : float
        ``uniform``: half-width of the interval (rad, m).
    sample_time : float or None
        ``white``: correlation time of the samples (s); ``None`` = the control period.
    channels : tuple of str
        Which of ``("x", "phi")`` are noisy.
    """

    kind: str = "none"
    power: float = 0.0
    amplitude: float = 0.0
    sample_time: float | None = None
    channels: tuple[str, ...] = field(default=CHANNELS)

    def __post_init__(self) -> None:
        if self.kind not in ("none", "white", "uniform"):
            raise ValueError(f"noise kind must be 'none', 'white' or 'uniform', got {self.kind!r}")
        for name in ("power", "amplitude"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"noise {name} must be a finite number >= 0, got {v!r}")
        if self.sample_time is not None and not (self.sample_time > 0 and math.isfinite(self.sample_time)):
            raise ValueError(f"noise sample_time must be > 0, got {self.sample_time!r}")
        bad = [c for c in self.channels if c not in CHANNELS]
        if bad:
            raise ValueError(f"noise channels must be among {CHANNELS}, got {bad}")
        object.__setattr__(self, "channels", tuple(self.channels))

    def std(self, Ts: float) -> float:
        """Standard deviation of one sample (rad or m) when sampled every ``Ts`` s."""
        return math.sqrt(self.variance(Ts))

    def variance(self, Ts: float) -> float:
        """Variance of one sample: ``power / sample_time`` (white), ``amplitude**2/3`` (uniform)."""
        if self.kind == "white":
            return self.power / (self.sample_time if self.sample_time is not None else Ts)
        if self.kind == "uniform":
            return self.amplitude**2 / 3.0
        return 0.0

    def hold_ticks(self, Ts: float) -> int:
        """Control ticks each noise sample is held (>= 1)."""
        if self.kind != "white" or self.sample_time is None:
            return 1
        return max(1, int(round(self.sample_time / Ts)))


class NoiseSource:
    """Draws the noise of each tick for both channels, shape ``(2, *batch_shape)``.

    Parameters
    ----------
    model : NoiseModel
        What to draw.
    Ts : float
        Control period (s).
    rng : numpy.random.Generator
        Seeded generator (the only source of randomness).
    batch_shape : tuple of int
        Extra dimensions (one independent noise stream per batch member).
    """

    def __init__(self, model: NoiseModel, Ts: float, rng: np.random.Generator, batch_shape: tuple[int, ...] = ()) -> None:
        self.model = model
        self.Ts = float(Ts)
        self.rng = rng
        self.shape = (2, *batch_shape)
        self._mask = np.array([c in model.channels for c in CHANNELS], dtype=float).reshape((2,) + (1,) * len(batch_shape))
        self._hold = model.hold_ticks(Ts)
        self._count = 0
        self._value = np.zeros(self.shape)

    def draw(self) -> np.ndarray:
        """Noise for the next tick: ``[n_x (m), n_phi (rad)]`` of shape ``(2, *batch_shape)``."""
        m = self.model
        if m.kind == "none":
            return self._value
        if self._count % self._hold == 0:
            if m.kind == "white":
                v = self.rng.standard_normal(self.shape) * m.std(self.Ts)
            else:
                v = self.rng.uniform(-m.amplitude, m.amplitude, self.shape)
            self._value = v * self._mask
        self._count += 1
        return self._value


def _copy(v: Any) -> Any:
    return v.copy() if isinstance(v, np.ndarray) else v


class DelayLine:
    """A FIFO of ``steps`` ticks: what goes in at tick k comes out at tick k + steps.

    Parameters
    ----------
    steps : int
        Delay in ticks (0 = pass-through).
    initial : object
        Value the line is filled with (output for the first ``steps`` ticks); arrays are
        copied on the way in, any other value is stored as is.
    """

    def __init__(self, steps: int, initial: Any) -> None:
        if steps < 0:
            raise ValueError(f"delay steps must be >= 0, got {steps}")
        self.steps = int(steps)
        self._buf = [_copy(initial) for _ in range(max(self.steps, 1))]
        self._i = 0

    def push(self, value: Any) -> Any:
        """Insert this tick's value and return the one from ``steps`` ticks ago."""
        if self.steps == 0:
            return value
        i = self._i
        out = self._buf[i]
        self._buf[i] = _copy(value)
        self._i = (i + 1) % self.steps
        return out

    def peek(self, j: int) -> np.ndarray:
        """The value :meth:`push` will return ``j`` pushes from now (``1 <= j <= steps``).

        It was inserted ``steps - j`` pushes ago, so it is already known: a lockstep HIL
        host can send sensor frames ahead of the board's answers.
        """
        if not 1 <= j <= self.steps:
            raise ValueError(f"can only look 1..{self.steps} ticks ahead, asked {j}")
        return _copy(self._buf[(self._i + j - 1) % self.steps])


class SensorModel:
    """The board's sensors: noise, quantisation to ADC/encoder counts, measurement delay.

    Parameters
    ----------
    params : RobotParams
        Sensor parameters (``adc_bits, pot_range, pot_offset, enc_cpr, r_wheel, rate``).
    noise : NoiseModel, optional
        Measurement noise (default none).
    delay : float, optional
        Measurement delay (s); default ``params.delay``.
    rng : numpy.random.Generator or int, optional
        Generator or seed (default seed 0).
    batch_shape : tuple of int
        Batch dimensions of the states fed to :meth:`measure`.
    """

    def __init__(
        self,
        params: RobotParams,
        *,
        noise: NoiseModel | None = None,
        delay: float | None = None,
        rng: np.random.Generator | int | None = None,
        batch_shape: tuple[int, ...] = (),
    ) -> None:
        self.params = params
        self.Ts = 1.0 / params.rate
        self.delay = params.delay if delay is None else float(delay)
        self.delay_steps = delay_steps(self.delay, params.rate)
        self.noise_model = noise if noise is not None else NoiseModel()
        if not isinstance(rng, np.random.Generator):
            rng = np.random.default_rng(0 if rng is None else rng)
        self.rng = rng
        self.batch_shape = tuple(batch_shape)
        self._noise = NoiseSource(self.noise_model, self.Ts, rng, self.batch_shape)
        self._line: DelayLine | None = None
        # constants of the scalar fast path (one robot, plain Python ints and floats)
        self._scalar = self.batch_shape == ()
        self._cpr = float(adc_counts_per_rad(params))
        self._cpm = float(enc_counts_per_m(params))
        self._off = float(params.pot_offset)
        self._full = 2 ** int(params.adc_bits) - 1
        self._noisy = self.noise_model.kind != "none"
        amp, w = inl_terms(params)
        self._inl, self._inl_w = float(amp), float(w)

    def quantise(self, x: np.ndarray | float, phi: np.ndarray | float, noise: np.ndarray | None = None) -> Any:
        """Counts ``[enc, adc]`` for a state, without delay.

        Returns an int64 array of shape ``(2, *batch)``; for an unbatched model a tuple of two
        Python ints (same values: ``round`` and ``numpy.rint`` both round half to even).
        """
        nx, nphi = (0.0, 0.0) if noise is None else (noise[0], noise[1])
        if self._scalar:
            c = self._off + (float(phi) + float(nphi)) * self._cpr
            if self._inl:
                c = c + self._inl * math.sin(self._inl_w * c)
            adc = round(c)
            adc = 0 if adc < 0 else (self._full if adc > self._full else adc)
            return round((float(x) + float(nx)) * self._cpm) % ENC_MODULUS, adc
        return np.stack([x_to_encoder(x, self.params, nx), phi_to_adc(phi, self.params, nphi)])

    def reset(self, x: np.ndarray | float, phi: np.ndarray | float) -> None:
        """Fill the delay line with the noiseless reading of the resting initial state."""
        self._line = DelayLine(self.delay_steps, self.quantise(x, phi))

    def measure(self, x: np.ndarray | float, phi: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Take this tick's reading and return the one the board sees now (delayed).

        Parameters
        ----------
        x, phi : float or ndarray of ``batch_shape``
            True cart position (m) and tilt (rad) at this tick.

        Returns
        -------
        (adc, enc) : tuple of int64 ndarray (Python ints when unbatched)
            ADC counts (0..2**adc_bits-1) and encoder counter (0..65535), ``batch_shape``.
        """
        if self._line is None:
            self.reset(x, phi)
        reading = self.quantise(x, phi, self._noise.draw() if self._noisy else None)
        out = self._line.push(reading)
        return out[1], out[0]

    def peek(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """``(adc, enc)`` that :meth:`measure` will return ``j`` ticks from now (``1 <= j <= delay_steps``)."""
        if self._line is None:
            raise ValueError("no reading taken yet")
        out = self._line.peek(j)
        return out[1], out[0]

    def decode(self, adc: np.ndarray | int, enc: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """Convert counts back to ``(x (m), phi (rad))`` (encoder read as signed 16-bit)."""
        return encoder_to_x(enc, self.params), adc_to_phi(adc, self.params)

