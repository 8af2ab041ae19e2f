"""The errors of the HIL loop: the loop could not run, or a tick was lost or repeated."""

from __future__ import annotations

__all__ = ["HilError", "TickError"]


class HilError(RuntimeError):
    """The HIL loop could not run or went wrong (the message says where)."""


class TickError(HilError):
    """The firmware's answer did not carry the tick just sent (a tick lost or repeated)."""
