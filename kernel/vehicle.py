"""Vehicle parameters: what the controller believes about the airframe (docs/hardware.md)."""

from __future__ import annotations

from dataclasses import dataclass

from cfknode.kernel.setting import setting

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class VehicleConfig:
    mass: float = setting(unit="kg", low=0.015, high=0.1,
        doc="firmware CF_MASS since 2025.09 (docs/hardware.md#vehicle-parameters)")
    inertia: Vec3 = setting(unit="kg m^2", low=5e-06, high=0.0005,
        doc="diagonal; Crazyswarm2 / Foerster 2015, rounded (docs/hardware.md#vehicle-parameters)")
    arm_length: float = setting(unit="m", low=0.02, high=0.1,
        doc="motor to centre; firmware ARM_LENGTH (docs/hardware.md#vehicle-parameters)")
    thrust_max_per_motor: float = setting(unit="N", low=0.05, high=0.5,
        doc="N at command 65535; firmware THRUST_MAX, fw >= 2025.12 (docs/hardware.md#thrust-map)")
    thrust_cmd_clamp: int = setting(low=20000, high=65535,
        doc="RPYT commander MAX_THRUST (docs/hardware.md#rpyt-setpoint)")
    thrust_to_torque: float = setting(unit="m", low=0.001, high=0.05,
        doc="yaw torque per unit thrust; firmware THRUST2TORQUE 2.1+ (docs/hardware.md#vehicle-parameters)")
    motor_time_constant: float = setting(unit="s", low=0.005, high=0.2,
        doc="first-order motor thrust lag (docs/hardware.md#vehicle-parameters)")
    gravity: float = setting(unit="m/s^2", low=9.0, high=10.5, doc="gravitational acceleration")

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
