"""Backends: the simulator and a Crazyflie (real, or the simulator behind sim://)."""
