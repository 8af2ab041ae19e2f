"""Hardware-in-the-loop: the firmware closed around the simulated plant (session, lockstep loop, faults, soak)."""
