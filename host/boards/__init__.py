"""Where the firmware runs: MicroPython interpreters, the flash bundle, the virtual and the emulated board."""
