"""make bench: the speed figures, measured side by side in one run."""
