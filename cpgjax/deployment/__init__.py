"""What drives the robot's 1 kHz loop (``cpgjax.hardware_io``): a deploy run (replay or online optimization), the
online trials and their optimizer process, the foot-sensor calibration, and the run's per-tick log."""
