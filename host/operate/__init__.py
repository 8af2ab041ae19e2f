"""Operating a board: the library behind ``upright board`` (and the dashboard).

* :mod:`host.operate.board` -- :class:`~host.operate.board.Board`: connect (identity checked),
  status, arm/disarm/clear with the host heartbeat kept going, parameters by name, gain upload;
* :mod:`host.operate.record` -- every telemetry frame to CSV or Parquet, losses counted;
* :mod:`host.operate.calibrate` -- the commissioning computations and the robot TOML;
* :mod:`host.operate.excite` -- identification runs: the firmware's PRBS (EXCITE), recorded.
"""
