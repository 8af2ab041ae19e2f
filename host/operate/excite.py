"""Identification excitation: a bounded PRBS on the cart reference, played by the host.

The firmware has no excitation generator of its own; the host sends ``set_reference`` at
each bit of a maximum-length pseudo-random binary sequence (an LFSR), at its own pace, and
records the telemetry like ``upright board log`` (the commanded reference in the column
``ref_cmd``).  The amplitude is bounded by the board's ``ref_limit_um`` and by
:data:`MAX_AMPLITUDE_M`; the reference goes back to 0 at the end, on Ctrl-C and on error.
"""

from __future__ import annotations

from typing import Iterator

__all__ = ["MAX_AMPLITUDE_M", "prbs_bits", "prbs_levels"]

MAX_AMPLITUDE_M = 0.2
"""Largest PRBS amplitude accepted (m): a tenth of the report's track would already be a lot."""

# feedback taps (Fibonacci LFSR, bits numbered from 1) of maximum-length sequences
_TAPS = {5: (5, 3), 6: (6, 5), 7: (7, 6), 8: (8, 6, 5, 4), 9: (9, 5), 10: (10, 7)}


def prbs_bits(order: int = 7, seed: int = 1) -> Iterator[int]:
    """Endless maximum-length PRBS of period ``2**order - 1`` as 0/1 bits."""
    if order not in _TAPS:
        raise ValueError(f"PRBS order must be one of {sorted(_TAPS)}, got {order}")
    mask = (1 << order) - 1
    state = (seed & mask) or 1
    taps = _TAPS[order]
    while True:
        bit = 0
        for t in taps:
            bit ^= (state >> (t - 1)) & 1
        yield state & 1
        state = ((state >> 1) | (bit << (order - 1))) & mask


def prbs_levels(amplitude: float, n: int, order: int = 7, offset: float = 0.0) -> list[float]:
    """The first ``n`` reference levels: ``offset +- amplitude``."""
    if not 0 < amplitude <= MAX_AMPLITUDE_M:
        raise ValueError(f"amplitude must be in (0, {MAX_AMPLITUDE_M}] m, got {amplitude!r}")
    g = prbs_bits(order)
    return [offset + (amplitude if next(g) else -amplitude) for _ in range(n)]
