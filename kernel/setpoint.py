"""Attitude setpoints, and how the Crazyflie firmware reads one (docs/hardware.md).

``AttitudeSetpoint`` holds the arguments of cflib's ``send_setpoint(roll, pitch, yawrate,
thrust)``: right-handed ZYX angles in degrees (positive pitch = nose down), the yaw rate
clockwise-positive (the firmware negates it), and the 16-bit thrust command.

``read_setpoint`` is the firmware's side as a pure function: collective thrust in newtons
and the desired attitude, with the yaw integrator. Anyone flying cfknode's commands in
another simulator calls it instead of rebuilding these conventions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from cfknode.kernel.vehicle import VehicleConfig

RPYT_MIN_THRUST = 1000  # the RPYT commander turns smaller commands into 0


@dataclass(frozen=True)
class AttitudeSetpoint:
    """Arguments of cflib ``send_setpoint(roll, pitch, yawrate, thrust)``."""

    roll_deg: float
    pitch_deg: float
    yawrate_deg: float
    thrust: int


@dataclass(frozen=True)
class FirmwareTarget:
    """What the firmware's attitude controller aims for after reading one setpoint."""

    thrust_n: float  # collective thrust [N] along the body z axis
    roll: float  # rad, right-handed ZYX
    pitch: float  # rad, right-handed ZYX (positive = nose down)
    yaw: float  # rad, the integrated desired yaw
    yaw_rate: float  # rad/s, counter-clockwise positive

    @property
    def quaternion(self) -> tuple[float, float, float, float]:
        """The desired attitude as a scalar-first quaternion (w, x, y, z), body to world."""
        cr, sr = math.cos(self.roll / 2), math.sin(self.roll / 2)
        cp, sp = math.cos(self.pitch / 2), math.sin(self.pitch / 2)
        cy, sy = math.cos(self.yaw / 2), math.sin(self.yaw / 2)
        return (
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        )


def thrust_command(force: float, vehicle: VehicleConfig) -> int:
    """Collective force [N] -> RPYT thrust command, rounded and clamped to [0, thrust_cmd_clamp]."""
    cmd = round(force / vehicle.newton_per_cmd)
    return min(max(cmd, 0), vehicle.thrust_cmd_clamp)


def rpyt_thrust(raw: int, clamp: int) -> int:
    """The thrust command the RPYT commander keeps: below 1000 it is 0, above the clamp the clamp."""
    return 0 if raw < RPYT_MIN_THRUST else min(int(raw), int(clamp))


def ccw_yaw_rate_deg(yawrate_deg: float) -> float:
    """The RPYT yaw rate is clockwise-positive; the firmware flies its negation (CCW-positive)."""
    return -float(yawrate_deg)


def integrate_yaw_deg(yaw_desired_deg: float, ccw_rate_deg: float, dt: float) -> float:
    """The firmware's desired-yaw integrator in rate mode, wrapped to [-180, 180] degrees."""
    yaw = yaw_desired_deg + ccw_rate_deg * dt
    return (yaw + 180.0) % 360.0 - 180.0


def read_setpoint(sp: AttitudeSetpoint, vehicle: VehicleConfig, yaw_desired: float, dt: float) -> FirmwareTarget:
    """The firmware's reading of ``sp`` held for ``dt`` seconds from desired yaw ``yaw_desired`` [rad].

    Thrust: below 1000 is 0, above ``vehicle.thrust_cmd_clamp`` is clamped, then mapped to
    newtons with the vehicle's linear thrust map. Roll and pitch are taken as given (cflib
    negates pitch on the wire and the firmware's legacy pitch undoes it). The yaw rate is
    negated and integrated into the desired yaw. Call it once per firmware step with the
    previous result's ``yaw`` to reproduce the integrator.
    """
    cmd = rpyt_thrust(int(sp.thrust), vehicle.thrust_cmd_clamp)
    rate_deg = ccw_yaw_rate_deg(sp.yawrate_deg)
    yaw_deg = integrate_yaw_deg(math.degrees(yaw_desired), rate_deg, dt)
    return FirmwareTarget(
        thrust_n=cmd * vehicle.newton_per_cmd,
        roll=math.radians(sp.roll_deg),
        pitch=math.radians(sp.pitch_deg),
        yaw=math.radians(yaw_deg),
        yaw_rate=math.radians(rate_deg),
    )
