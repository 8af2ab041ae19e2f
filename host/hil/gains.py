"""Which gain table the board runs for a scenario: the design's, adjusted to the scenario's sensor noise.

A scenario that puts measurement noise on the sensors gets the design's table with the
estimator designed for that noise (:func:`design_noise`) and, where the firmware's encoder
plausibility check would take the noise for lost counts, that limit widened
(:func:`encoder_jump_limit`); :func:`gain_table` builds (and caches) the blob
:meth:`host.hil.session.HilSession.prepare` uploads.
"""

from __future__ import annotations

import math

from sim.params import RobotParams, load_params
from sim.scenario import Scenario

__all__ = ["gain_table", "design_noise", "encoder_jump_limit"]

_TABLES: dict[tuple[int | None, tuple[float, float] | None], tuple[bytes, str]] = {}


def gain_table(encj: int | None, sigma: tuple[float, float] | None = None) -> tuple[bytes, str]:
    """The design's table (:mod:`host.design.export`, default robot) as ``(blob, label)``.

    With the estimator designed for measurement noise ``sigma`` ``(m, rad)`` and the
    encoder step limit ``ENCJ`` replaced by ``encj`` counts per tick; ``(None, None)`` is
    the firmware's own table (label ``"firmware default"``).
    """
    key = (encj, sigma)
    if key not in _TABLES:
        from host.design.discrete import controller_ss
        from host.design.export import export

        labels = []
        if sigma is None:
            fd = export()
        else:
            fd = export(ctrl=controller_ss(load_params(), sigma_meas=sigma))
            labels.append(f"estimator for noise {sigma[0]:.3g} m / {sigma[1]:.3g} rad")
        if encj is not None:
            fd.tables["ENCJ"] = [int(encj)]
            labels.append(f"encoder step limit {encj} counts/tick")
        _TABLES[key] = (fd.blob(), ", ".join(labels) or "firmware default")
    return _TABLES[key]


def design_noise(scenario: Scenario, params: RobotParams) -> tuple[float, float] | None:
    """Measurement noise ``(m, rad)`` the estimator is designed for in this scenario, or
    ``None`` when the firmware's own table (default sensor noise) serves.

    See :func:`host.design.discrete.sigma_meas_for`.
    """
    from host.design.discrete import SIGMA_MEAS, sigma_meas_for

    sig = sigma_meas_for(scenario, params)
    return None if sig == tuple(SIGMA_MEAS) else sig


def encoder_jump_limit(scenario: Scenario, params: RobotParams) -> int | None:
    """Encoder plausibility limit (counts per tick) a noisy scenario needs, or ``None``.

    The firmware faults (``F_ENC_JUMP``) when two encoder readings differ by more than the
    cart can move in one tick (2x its no-load speed).  Measurement noise on the cart
    position -- which a real quadrature encoder does not have, but the report's noise
    scenarios add "on both outputs" -- makes consecutive readings differ by up to twice
    the noise amplitude (uniform) or about 9 sigma (white, Gaussian: 6 sigma of a
    difference).  When that exceeds the default limit, the limit is widened by it.

    Returns
    -------
    int or None
        The widened limit, or ``None`` when the default table serves.
    """
    from sim.sensors import enc_counts_per_m

    n = scenario.noise
    if n.kind == "none" or "x" not in n.channels:
        return None
    p = scenario.apply(params)
    cpm = enc_counts_per_m(p)
    if n.kind == "uniform":
        spread = 2.0 * n.amplitude * cpm
    else:
        spread = 9.0 * n.std(1.0 / p.rate) * cpm
    base = 2.0 * p.V_supply * p.r_wheel / (p.kt * p.gear) / p.rate * cpm + 2.0
    if spread < 1.0:
        return None
    return int(min(30000, math.ceil(base + spread + 2)))
