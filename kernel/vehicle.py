"""Vehicle parameters: what the controller believes about the airframe (docs/hardware.md)."""

from __future__ import annotations

from dataclasses import dataclass

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class VehicleConfig:
    mass: float  # kg
    inertia: Vec3  # kg m^2, body axes
    arm_length: float  # m, centre to motor
    thrust_max_per_motor: float  # N at command 65535
    thrust_cmd_clamp: int  # the firmware's RPYT thrust clamp (60000)
    thrust_to_torque: float  # m, yaw moment per newton of thrust
    motor_time_constant: float  # s, first-order motor lag
    gravity: float  # m/s^2

    @property
    def newton_per_cmd(self) -> float:
        """Collective force per unit of thrust command (all four motors)."""
        return 4.0 * self.thrust_max_per_motor / 65535.0

    @property
    def max_thrust(self) -> float:
        """Collective force at the RPYT clamp, N."""
        return self.thrust_cmd_clamp * self.newton_per_cmd

    @property
    def thrust_to_weight(self) -> float:
        """Collective thrust at the clamp over weight."""
        return self.max_thrust / (self.mass * self.gravity)
