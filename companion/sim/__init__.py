"""The built-in simulator: quadrotor dynamics, gates, sensors, geometric camera, scoring, simulated PX4."""
