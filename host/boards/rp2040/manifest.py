"""Frozen manifest of the emulated board's firmware (MicroPython 1.25 rp2 port, BOARD=RPI_PICO).

The port's own ``boards/manifest.py`` minus its ``require()`` lines: those name micropython-lib
packages (onewire, ds18x20, dht, neopixel), and micropython-lib is not in Debian. What stays is
the port's own modules (``_boot.py``, ``_boot_fat.py``, ``rp2.py``) and ``extmod/asyncio``.
Read by MicroPython's ``tools/makemanifest.py``, not imported by CPython;
``host.boards.rp2040.build`` passes it as ``-DMICROPY_FROZEN_MANIFEST``.
"""

freeze("$(PORT_DIR)/modules")  # noqa: F821 (defined by makemanifest)
include("$(MPY_DIR)/extmod/asyncio")  # noqa: F821
