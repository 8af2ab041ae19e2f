"""The firmware's integral action on the cart position as a linear controller (issue 24 item 3).

``firmware/controller.py``: ``u += KI integ``, ``integ += (r - x_hat)`` per tick, clamped,
conditional integration while saturated.  :class:`IntegralController` is that law around a
:class:`~host.design.discrete.DiscreteController`, as the batch simulator and the scenario
simulator run it: one more state ``e' = e + Ts (r - x_hat)``, ``u += ki e`` (the anti-windup is
not modelled: it only acts while the force saturates).  A design candidate with ``ki``
(:class:`host.design.robust.Candidate`) builds it.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

__all__ = ["IntegralController"]


class IntegralController:
    """A :class:`~host.design.discrete.DiscreteController` with the firmware's integral action.

    ``u = Cc z + Dc v + ki e``, ``e[k+1] = e[k] + Ts (x_ref - x_hat[k])`` with ``x_hat`` the
    controller's predicted cart position (``estimate(z, v)[0]``, what the firmware integrates),
    appended as the last state; ``ki`` carries the sign of the reference gain (as the export's
    ``KI`` row).  Offers the attributes the batch simulator, :class:`~host.design.robust.MeasuredStart`
    and :func:`sim.plantsim.run_scenario_float` use; the others come from ``inner``.
    """

    def __init__(self, inner: Any, ki: float) -> None:
        self.inner = inner
        self.ki = float(ki)
        n = int(inner.Ac.shape[0])
        Ts = float(inner.Ts)
        # x_hat = hz z + hv v (linear: probe the estimate)
        hz = np.array([inner.estimate(np.eye(n)[i], np.zeros(3))[0] for i in range(n)])
        hv = np.array([inner.estimate(np.zeros(n), np.eye(3)[i])[0] for i in range(3)])
        k = math.copysign(self.ki, float(getattr(inner, "kr", 1.0)) or 1.0)
        self.Ac = np.zeros((n + 1, n + 1))
        self.Ac[:n, :n] = inner.Ac
        self.Ac[n, :n] = -Ts * hz
        self.Ac[n, n] = 1.0
        self.Bc = np.zeros((n + 1, 3))
        self.Bc[:n] = np.asarray(inner.Bc).reshape(n, 3)
        self.Bc[n] = -Ts * hv
        self.Bc[n, 2] += Ts
        self.Cc = np.zeros((1, n + 1))
        self.Cc[0, :n] = np.asarray(inner.Cc).reshape(n)
        self.Cc[0, n] = k
        self.Dc = np.asarray(inner.Dc, dtype=float).reshape(1, 3).copy()
        self.Bu = np.zeros((n + 1, 1))
        self.Bu[:n] = np.asarray(inner.Bu).reshape(n, 1)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    @property
    def n(self) -> int:
        """Controller states (the inner controller's plus the integrator)."""
        return int(self.Ac.shape[0])

    def estimate(self, z: np.ndarray, v: Sequence[float]) -> np.ndarray:
        """The inner controller's predicted state (the integrator does not enter it)."""
        return self.inner.estimate(np.asarray(z)[:-1], v)

    def output(self, z: np.ndarray, v: Sequence[float]) -> float:
        """Unsaturated force ``Cc z + Dc v`` (N)."""
        return float((self.Cc @ z + self.Dc @ np.asarray(v, dtype=float))[0])

    def saturate(self, u: float) -> float:
        """Clip to the force clamp."""
        return min(max(u, -self.inner.u_max), self.inner.u_max)

    def step(self, z: np.ndarray, v: Sequence[float], u_sat: float) -> np.ndarray:
        """Next state."""
        return self.Ac @ z + self.Bc @ np.asarray(v, dtype=float) + self.Bu[:, 0] * u_sat

    def tick(self, z: np.ndarray, v: Sequence[float]) -> tuple[float, float, np.ndarray]:
        """``(u, u_sat, z_next)``."""
        u = self.output(z, v)
        us = self.saturate(u)
        return u, us, self.step(z, v, us)

    def initial_state(self, v: Sequence[float] | None = None) -> np.ndarray:
        """The inner start state, integrator empty."""
        return np.append(self.inner.initial_state(v), 0.0)
