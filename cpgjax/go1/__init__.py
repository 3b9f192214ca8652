"""Facts about the Unitree Go1: constants, the MJCF model and scenarios, leg kinematics, attitude conventions and the
sensor model (what the robot's sensors report)."""
