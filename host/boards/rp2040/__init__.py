"""The emulated Raspberry Pi Pico: MicroPython's rp2 port built from Debian sources, run in rp2040js."""
