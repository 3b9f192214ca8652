"""The robot side: the Go1 wire protocol, transports, safety, the compiled controller, foot-force calibration,
online trials on the robot, the loopback simulated Go1 and ``cpgjax deploy``. The 1 kHz loop is
``cpgjax.hardware_io``."""
