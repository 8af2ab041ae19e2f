"""Catch mode: a second, more aggressive force row for large tilts (issue 15 item 3).

The shipped tracking design (:data:`host.design.discrete.Q_DEFAULT`, clamp at 4.4 m/s^2
from upright) cannot recover from 0.3 rad: holding 0.3 rad alone takes g tan 0.3 = 3 m/s^2,
and its position loop spends the clamp's remaining authority on the cart.  A design that
weighs the tilt far above the cart position recovers, but is too slow on a reference step
(``docs/parameters.md``).  The firmware therefore carries both rows and switches between
them (``firmware/controller.py``, ``Controller.schedule``):

* **shared**: the Kalman filter of the delayed state, the predictor over the stored forces
  and the forces themselves -- only the state-feedback row ``u = -K_c xh + kr_c r`` and its
  clamp change, so the switch is a compare and a pointer swap;
* **enter** when the a-priori estimate of the (delayed) tilt exceeds ``phi_on``;
* **hand back** only once ``|phi| < phi_off`` and ``|phidot| < w_off`` (hysteresis), from
  the reference that makes the tracking row give the catch row's force on the same
  estimator state (accepted only if they then differ by at most ``du`` newtons: bumpless
  transfer); that reference then moves to the set one at ``r_rate`` m/s (the cart's
  gentle return).

The catch row is an LQR on the same discrete plant with ``Q_CATCH``/``R_CATCH`` and a
clamp ``A_CATCH`` m/s^2 from upright (:func:`host.design.discrete.force_clamp`): the cart
acceleration the report allows is 5 m/s^2 and ``atan(5/g)`` = 0.47 rad is the largest tilt
that can be held at all, so the clamp sits just under it.  :func:`catch_tables` gives the
firmware's integer entries (``CATCH``, ``KFC``, ``KBC``, ``KRC``, ``KIC``, ``SKC``) for
:func:`host.design.export.export`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
import control as ct
import numpy as np

from host.design.discrete import DiscreteController, force_clamp
from sim.params import RobotParams

__all__ = ["CatchDesign", "CATCH_DEFAULT", "catch_gain", "catch_rows", "catch_clamp", "design_summary", "physical_bound"]

# chosen by a random search (300 designs, weights log-uniform, clamp 4.3-4.5 m/s^2, hand-back
# thresholds and ramp speed) with the firmware in the loop (host/bench/catch.py): tilt_0p3
# settles in 1.59 s at 4.70 m/s^2, the largest recoverable tilt is 0.334 rad (the cart's travel
# and the drive's 1.8 m/s limit it), the soft_pendulum plant is caught too (2.57 s, 4.74 m/s^2)
Q_CATCH = (0.035, 0.83, 0.41, 0.013)
R_CATCH = 0.027
A_CATCH = 4.4  # m/s^2: the catch row's acceleration clamp (the back-EMF compensation adds up to ~0.3)


@dataclass(frozen=True)
class CatchDesign:
    """Weights, clamp and switching rule of the catch row.

    Attributes
    ----------
    Q : tuple of 4 float
        Diagonal continuous LQR state weight (x, xdot, phi, phidot).
    R : float
        Continuous input weight.
    a_cmd : float
        Force clamp as cart acceleration from upright (m/s^2).
    phi_on, phi_off : float
        Tilt (rad) above which catch mode starts and below which the hand-back may happen.
    du : float
        Largest force difference (N) between the two rows accepted at the hand-back.
    w_off : float
        Tilt rate (rad/s) below which the hand-back may happen (with ``|phi| < phi_off``).
    r_rate : float
        Speed (m/s) at which the tracking row's reference moves from where the hand-back
        started it (the reference that makes both rows agree) to the set reference.
    """

    Q: tuple[float, ...] = Q_CATCH
    R: float = R_CATCH
    a_cmd: float = A_CATCH
    phi_on: float = 0.2
    phi_off: float = 0.12
    du: float = 0.05
    r_rate: float = 0.05
    w_off: float = 0.4

    def __post_init__(self) -> None:
        if len(self.Q) != 4 or any(not (q >= 0 and math.isfinite(q)) for q in self.Q) or not self.R > 0:
            raise ValueError(f"Q must be 4 non-negative weights and R > 0, got Q={self.Q}, R={self.R}")
        if not (0 < self.phi_off <= self.phi_on < math.pi / 2):
            raise ValueError(f"need 0 < phi_off <= phi_on < pi/2, got {self.phi_off}, {self.phi_on}")
        if not (self.a_cmd > 0 and self.du >= 0 and self.r_rate > 0 and self.w_off > 0):
            raise ValueError(f"a_cmd must be > 0 and du >= 0, got {self.a_cmd}, {self.du}")


CATCH_DEFAULT = CatchDesign()


def physical_bound(params: RobotParams) -> float:
    """Largest tilt (rad) a cart limited to ``params.a_max`` can hold at rest: ``atan(a_max / g)``."""
    return math.atan(float(params.a_max) / float(params.physical["g"]))


def catch_gain(ctrl: DiscreteController, design: CatchDesign = CATCH_DEFAULT) -> np.ndarray:
    """The catch row's discrete state feedback ``K_c`` (1, 4) on the controller's own plant.

    ``dlqr(Ad, Bd, Q Ts, R Ts)`` with the same mapping of continuous weights as
    :func:`host.design.discrete.controller_ss`.
    """
    Ad, Bd, Ts = ctrl.Ad, ctrl.Bd, ctrl.Ts
    K, _, _ = ct.dlqr(Ad, Bd, np.diag(np.asarray(design.Q, dtype=float)) * Ts, np.array([[design.R * Ts]]))
    K = np.asarray(K, dtype=float).reshape(1, 4)
    if np.max(np.abs(np.linalg.eigvals(Ad - Bd @ K))) >= 1.0:
        raise ValueError("the catch feedback does not stabilise the discrete plant")
    return K


def catch_rows(ctrl: DiscreteController, design: CatchDesign = CATCH_DEFAULT) -> tuple[np.ndarray, np.ndarray, float]:
    """``(Kf_c, kb_c, kr_c)``: the catch row in the firmware's structured form.

    ``u = -Kf_c xf - kb_c . b + kr_c r`` with ``Kf_c = K_c Ad^d``, ``kb_c[i] = K_c Ad^(d-1-i) Bd``
    and ``kr_c`` the unit-DC-gain precompensator of ``K_c``.
    """
    K = catch_gain(ctrl, design)
    Ad, Bd, d = ctrl.Ad, ctrl.Bd, ctrl.delay_steps
    Kf = (K @ np.linalg.matrix_power(Ad, d))[0]
    kb = np.array([(K @ np.linalg.matrix_power(Ad, d - 1 - i) @ Bd)[0, 0] for i in range(d)])
    cx = np.array([[1.0, 0.0, 0.0, 0.0]])
    kr = float(1.0 / (cx @ np.linalg.solve(np.eye(4) - Ad + Bd @ K, Bd))[0, 0])
    return Kf, kb, kr


def catch_clamp(params: RobotParams, design: CatchDesign = CATCH_DEFAULT) -> float:
    """The catch row's force clamp (N): ``design.a_cmd`` of cart acceleration from upright."""
    return force_clamp(params, design.a_cmd)


def design_summary(params: RobotParams, ctrl: DiscreteController, design: CatchDesign = CATCH_DEFAULT) -> dict[str, object]:
    """The catch row in SI units, for reports: K, kr, clamp, thresholds."""
    K = catch_gain(ctrl, design)
    _, _, kr = catch_rows(ctrl, design)
    return {"Q": list(design.Q), "R": design.R, "K": [float(v) for v in K[0]], "kr": kr,
            "u_max": catch_clamp(params, design), "a_cmd": design.a_cmd, "phi_on": design.phi_on,
            "phi_off": design.phi_off, "du": design.du}
