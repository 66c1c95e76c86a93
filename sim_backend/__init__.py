"""Simulated Crazyflie: rigid body, onboard firmware behaviour, scenarios, the sim:// cflib link."""
