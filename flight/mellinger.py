"""The Mellinger "acceleration to attitude" layer: world acceleration + yaw -> RPYT setpoint.

Conventions (docs/hardware.md#rpyt-setpoint): the angles are what cflib's ``send_setpoint`` takes,
right-handed ZYX Euler angles in degrees: positive pitch = nose down = accelerate toward
+x body, positive roll = right side down = accelerate toward -y body. cflib negates pitch
on the wire itself, so nothing is negated here. The RPYT yaw rate is clockwise-positive
(the firmware negates it), so the CCW rate we want is sent negated.

Runs at 400 Hz on 3-vectors, so it is plain ``math`` on floats (numpy costs more per call).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from cfknode.flight.settings import ControllerConfig
from cfknode.kernel.setpoint import AttitudeSetpoint, thrust_command
from cfknode.kernel.vehicle import VehicleConfig


def wrap_angle(angle: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True)
class CommandShaping:
    """What the fast adaptation layer tells the Mellinger layer (see flight/adaptation/).

    ``thrust_scale``: thrust is computed with this times the nominal mass. ``axis_gain``: the horizontal force
    is divided by it (the attitude loop delivers only that fraction of a tilt), bounded to 0.5..2. With
    ``cone`` the collective force is capped at the RPYT clamp (``max_thrust_fraction`` of it) by shrinking the
    horizontal part: altitude before tilt."""

    thrust_scale: float = 1.0
    axis_gain: tuple[float, float] = (1.0, 1.0)
    cone: bool = True


@dataclass(frozen=True)
class ShapedForce:
    force: tuple[float, float, float]  # N, world, as sent (after limits and effectiveness)
    applied_acc: tuple[float, float, float]  # the command as flown, in the model's input space (net acc, m/s^2)
    thrust_saturated: bool  # capped at the clamp
    tilt_saturated: bool  # horizontal part shrunk by the tilt limit or the cap


def shape_force(acc_world: Sequence[float], vehicle: VehicleConfig, controller: ControllerConfig,
                shaping: CommandShaping | None = None) -> ShapedForce:
    """Desired world acceleration -> desired collective force, with the tilt limit (keeping the vertical part).

    Without ``shaping`` this is exactly the nominal-mass layer."""
    m = vehicle.mass * (shaping.thrust_scale if shaping is not None else 1.0)
    ax, ay, az = float(acc_world[0]), float(acc_world[1]), float(acc_world[2])
    fx = m * ax
    fy = m * ay
    fz = m * (az + vehicle.gravity)
    thrust_sat = tilt_sat = False

    # Tilt limit on the desired force, keeping its vertical component (altitude first).
    # Asking for fz <= 0 (falling faster than gravity) cannot be flown: stay level, no thrust.
    if fz <= 0.0:
        tilt_sat = fx != 0.0 or fy != 0.0
        fx = fy = 0.0
        fz = max(fz, 0.0)
    else:
        f_xy = math.hypot(fx, fy)
        f_xy_max = fz * math.tan(math.radians(controller.max_tilt_deg))
        if shaping is not None and shaping.cone:
            f_max = controller.max_thrust_fraction * vehicle.max_thrust
            if fz >= f_max:
                thrust_sat = True
                fz = f_max
                f_xy_max = 0.0
            else:
                f_xy_max = min(f_xy_max, math.sqrt(f_max * f_max - fz * fz))
        if f_xy > f_xy_max:
            tilt_sat = True
            scale = f_xy_max / f_xy
            fx *= scale
            fy *= scale
    applied = (fx / m, fy / m, fz / m - vehicle.gravity)
    if shaping is not None:
        gx = min(max(shaping.axis_gain[0], 0.5), 2.0)
        gy = min(max(shaping.axis_gain[1], 0.5), 2.0)
        fx, fy = fx / gx, fy / gy
    return ShapedForce((fx, fy, fz), applied, thrust_sat, tilt_sat)


def command_saturated(shaped: ShapedForce, setpoint: AttitudeSetpoint, vehicle: VehicleConfig) -> bool:
    """Whether the command as sent was cut: the tilt limit or the cone shrank it, or its thrust sits at the
    RPYT clamp (the clamp also cuts a command the nominal layer passed through unshaped)."""
    return shaped.thrust_saturated or shaped.tilt_saturated or setpoint.thrust >= vehicle.thrust_cmd_clamp


def acc_to_setpoint(
    acc_world: Sequence[float],
    yaw_des: float,
    q: Sequence[float],
    vehicle: VehicleConfig,
    controller: ControllerConfig,
    shaping: CommandShaping | None = None,
) -> AttitudeSetpoint:
    """Desired world acceleration [m/s^2], desired yaw [rad] and the measured attitude
    ``q`` (wxyz, body to world) -> roll/pitch angles, yaw rate and thrust command."""
    return force_to_setpoint(shape_force(acc_world, vehicle, controller, shaping).force, yaw_des, q, vehicle, controller)


def measured_yaw(q: Sequence[float]) -> float:
    """The ZYX yaw [rad] of the attitude ``q`` (wxyz, body to world), in floats: the yaw the firmware's angle loop
    keeps its own and turns the roll and pitch it is sent about."""
    w, x, y, z = (float(c) for c in q)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def setpoint_body_z(roll_deg: float, pitch_deg: float, yaw: float) -> tuple[float, float]:
    """The world x and y of the body z axis the firmware rebuilds from a setpoint's roll and pitch about ``yaw``
    [rad]: the third column of Rz(yaw) Ry(pitch) Rx(roll), what ``force_to_setpoint`` solves for."""
    roll, pitch = math.radians(roll_deg), math.radians(pitch_deg)
    cy, sy, cr, sr = math.cos(yaw), math.sin(yaw), math.cos(roll), math.sin(roll)
    sp = math.sin(pitch)
    return cy * sp * cr + sy * sr, sy * sp * cr - cy * sr


def force_to_setpoint(
    force: Sequence[float],
    yaw_des: float,
    q: Sequence[float],
    vehicle: VehicleConfig,
    controller: ControllerConfig,
) -> AttitudeSetpoint:
    """Desired world force [N] (from ``shape_force``) -> RPYT setpoint for the measured attitude ``q``."""
    fx, fy, fz = (float(f) for f in force)
    w, x, y, z = (float(c) for c in q)
    yaw_meas = measured_yaw(q)

    # Desired body z axis, expressed in the frame turned by the *measured* yaw: the
    # firmware's angle loop rebuilds R = Rz(its own yaw) Ry(pitch) Rx(roll), so roll and
    # pitch must be the ZYX angles of an R_des whose yaw is the measured one. (Mellinger's
    # x_c = (cos yaw_des, sin yaw_des, 0) construction gives an R_des whose ZYX yaw differs
    # from that, which tilts the thrust up to 4 deg off at 30 deg tilt.) Yaw itself is
    # tracked through the yaw rate below.
    norm = math.sqrt(fx * fx + fy * fy + fz * fz)
    if norm > 0.0:
        zx, zy, zz = fx / norm, fy / norm, fz / norm
    else:
        zx, zy, zz = 0.0, 0.0, 1.0
    cy, sy = math.cos(yaw_meas), math.sin(yaw_meas)
    hx = cy * zx + sy * zy  # z_b_des in the yaw frame: Ry(pitch) Rx(roll) e3
    hy = -sy * zx + cy * zy  #   = (cos r sin p, -sin r, cos r cos p)
    roll = -math.asin(max(-1.0, min(1.0, hy)))
    pitch = math.atan2(hx, zz)

    # Collective thrust along the *measured* body z axis (third column of R(q)).
    bx = 2.0 * (x * z + w * y)
    by = 2.0 * (y * z - w * x)
    bz = 1.0 - 2.0 * (x * x + y * y)
    thrust = thrust_command(fx * bx + fy * by + fz * bz, vehicle)

    ccw_rate_deg = math.degrees(controller.yaw_rate_gain * wrap_angle(yaw_des - yaw_meas))
    limit = controller.max_yaw_rate_deg
    ccw_rate_deg = max(-limit, min(limit, ccw_rate_deg))

    return AttitudeSetpoint(
        roll_deg=math.degrees(roll),
        pitch_deg=math.degrees(pitch),
        yawrate_deg=-ccw_rate_deg,
        thrust=thrust,
    )
