"""PN-informed companion app: flies a PX4 quadrotor through moving gates from a monocular camera and the IMU."""

__version__ = "0.1.0"
