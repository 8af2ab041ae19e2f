"""upright simulation, the plant side only: parameters, nonlinear plant, motor, sensors, scenarios, metrics, plots, the batch simulator."""
