"""Control design: linear analysis, the report's controllers, discretisation with the sensor delay, fixed-point export."""
