"""What the robot's 1 kHz loop (``cpgjax.hardware_io``) uses: the Go1's wire format, transports, safety, the compiled
controller, the foot-force calibration's conversion, CPU placement, and the loopback simulated Go1. What drives the
loop (``cpgjax deploy``, online trials, calibration, the run log) is ``cpgjax.deployment``."""
