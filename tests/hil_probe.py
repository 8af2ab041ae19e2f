"""Test support: a virtual-board HIL session whose firmware runs under ``heap_lock`` and reports at exit.

The capability is the product's (``HilSession(probe=True)``, the probed HIL main of
:func:`host.boards.vport.probe_code`, also used by the soak); :class:`ProbeSession` is the
tests' shorthand for it.
"""

from __future__ import annotations

from typing import Any

from host.hil.faults import FaultError
from host.hil.session import HilSession

__all__ = ["ProbeSession"]


class ProbeSession(HilSession):
    """A virtual-board :class:`~host.hil.session.HilSession` whose firmware reports its heap and drops.

    The firmware is the unchanged :class:`firmware.main_hil.HilMain`, run under
    ``micropython.heap_lock()`` for the whole lockstep run (in real time the GC is disabled
    instead and the growth reported).  At exit it prints ``gc.mem_alloc()`` before and
    after the run, the steps and frames handled, and the decoder's drop counters; read them
    with :meth:`~host.hil.session.HilSession.probe` after :meth:`close`.
    """

    def __init__(self, *, link: str = "serial", mode: str = "lockstep", node: int = 1, **kw: Any) -> None:
        if kw.get("port") is not None:
            raise FaultError("ProbeSession runs the virtual board only (port=None)")
        kw.pop("port", None)
        super().__init__(None, link=link, mode=mode, node=node, probe=True, **kw)
