"""Studies above the design: Monte Carlo robustness, weight tuning, recoverable tilt, on Dask."""
