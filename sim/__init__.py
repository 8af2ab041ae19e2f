"""upright simulation: parameters, nonlinear plant, sensors, scenarios, metrics."""
