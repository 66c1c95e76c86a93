"""The firmware's building blocks: attitude PID gains and the PID itself, the legacy mixer, the
estimator's angle convention, setpoint records, and the commander's timing constants (docs/hardware.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from cfknode.kernel.setpoint import RPYT_MIN_THRUST  # noqa: F401 (the commander's rule, from the kernel)
from cfknode.sim_backend.vehicle import CMD_MAX

@dataclass(frozen=True)
class PidGains:
    kp: float
    ki: float
    kd: float
    i_limit: float


# platform_defaults_cf2.h (docs/hardware.md#attitude-controller): angle loops in deg -> deg/s, rate loops in deg/s -> PWM units.
ROLL_ANGLE_GAINS = PidGains(6.0, 3.0, 0.0, 20.0)
PITCH_ANGLE_GAINS = PidGains(6.0, 3.0, 0.0, 20.0)
YAW_ANGLE_GAINS = PidGains(6.0, 1.0, 0.35, 360.0)
ROLL_RATE_GAINS = PidGains(250.0, 500.0, 2.5, 33.3)
PITCH_RATE_GAINS = PidGains(250.0, 500.0, 2.5, 33.3)
YAW_RATE_GAINS = PidGains(120.0, 16.7, 0.0, 166.7)

INT16_LIMIT = 32767  # saturateSignedInt16 (symmetric so that negating is safe)
WDT_LEVEL_OUT = 0.5  # s, COMMANDER_WDT_TIMEOUT_STABILIZE
WDT_SHUTDOWN = 2.0  # s, COMMANDER_WDT_TIMEOUT_SHUTDOWN
IS_FLYING_HYSTERESIS = 2.0  # s, IS_FLYING_HYSTERESIS_THRESHOLD
ESTOP_WATCHDOG_TIMEOUT = 1.0  # s, DEFAULT_EMERGENCY_STOP_WATCHDOG_TIMEOUT (supervisor.c)
SUPERVISOR_PERIOD = 1.0 / 25.0  # s, RATE_SUPERVISOR
_TIME_TOL = 1e-9

# Commander priorities (commander.h).
PRIORITY_DISABLE = 0
PRIORITY_HIGH_LEVEL = 1
PRIORITY_CRTP = 2

# Internal supervisor states -> the names in the architecture.
_PUBLIC_STATE = {
    "ready": "idle",
    "flying": "flying",
    "warning_level_out": "warning_level_out",
    "except_free_fall": "locked",
    "locked": "locked",
    "landed": "landed",
}
_MOTORS_ALLOWED = frozenset({"ready", "flying", "warning_level_out", "landed"})


@dataclass(frozen=True)
class Setpoint:
    """A commander setpoint as the firmware holds it.

    ``pitch`` is the legacy pitch (+ = nose up), ``yaw_rate`` is CCW-positive [deg/s].
    ``attitude_mode`` is False for null setpoints (all modes disabled: motors off).
    """

    timestamp: float
    roll: float
    pitch: float
    yaw_rate: float
    thrust: int
    source: str  # "boot" | "rpyt" | "stop" | "high_level"
    attitude_mode: bool


@dataclass(frozen=True)
class ExtPose:
    t: float
    position: tuple[float, float, float]
    quaternion_xyzw: tuple[float, float, float, float]


def _null_setpoint(t: float, source: str) -> Setpoint:
    return Setpoint(t, 0.0, 0.0, 0.0, 0, source, False)


def cap_angle(deg: float) -> float:
    """Wrap to [-180, 180] degrees."""
    while deg > 180.0:
        deg -= 360.0
    while deg < -180.0:
        deg += 360.0
    return deg


def _saturate_int16(value: float) -> int:
    if value > INT16_LIMIT:
        return INT16_LIMIT
    if value < -INT16_LIMIT:
        return -INT16_LIMIT
    return int(value)  # C cast: truncation toward zero


def legacy_mixer(thrust: float, roll: int, pitch: int, yaw: int) -> tuple[int, int, int, int]:
    """Legacy quadrotor power distribution (docs/hardware.md#mixer), pitch in the legacy sense (+ = nose up).

    If any motor would exceed 65535, all four are lowered by the excess, which keeps the
    differences (the attitude authority) at the cost of thrust; then each is clamped to
    0..65535 (idle thrust 0 on an auto-arming CF2.1).
    """
    r = int(roll / 2.0)
    p = int(pitch / 2.0)
    m1 = int(thrust - r + p + yaw)
    m2 = int(thrust - r - p - yaw)
    m3 = int(thrust + r - p + yaw)
    m4 = int(thrust + r + p - yaw)
    excess = max(m1, m2, m3, m4) - CMD_MAX
    if excess > 0:
        m1 -= excess
        m2 -= excess
        m3 -= excess
        m4 -= excess
    return (min(max(m1, 0), CMD_MAX), min(max(m2, 0), CMD_MAX), min(max(m3, 0), CMD_MAX), min(max(m4, 0), CMD_MAX))


def firmware_attitude(qw: float, qx: float, qy: float, qz: float) -> tuple[float, float, float]:
    """(roll, legacy pitch, yaw) in degrees as the firmware's estimator reports them (ZYX, pitch negated)."""
    roll = math.atan2(2.0 * (qw * qx + qy * qz), 1.0 - 2.0 * (qx * qx + qy * qy))
    s = 2.0 * (qw * qy - qz * qx)
    pitch_rh = math.asin(1.0 if s > 1.0 else -1.0 if s < -1.0 else s)
    yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return math.degrees(roll), -math.degrees(pitch_rh), math.degrees(yaw)


class _Pid:
    """pid.c: P on the error, D on the measurement, clamped integral, optional yaw wrapping."""

    __slots__ = ("kp", "ki", "kd", "i_limit", "dt", "integ", "prev_measured", "wrap")

    def __init__(self, gains: PidGains, dt: float, wrap: bool = False) -> None:
        self.kp, self.ki, self.kd, self.i_limit = gains.kp, gains.ki, gains.kd, gains.i_limit
        self.dt = dt
        self.wrap = wrap
        self.integ = 0.0
        self.prev_measured = 0.0

    def reset(self, measured: float) -> None:
        self.integ = 0.0
        self.prev_measured = measured

    def update(self, desired: float, measured: float) -> float:
        error = desired - measured
        delta = self.prev_measured - measured
        if self.wrap:
            error = cap_angle(error)
            delta = cap_angle(delta)
        self.prev_measured = measured
        integ = self.integ + error * self.dt
        lim = self.i_limit
        self.integ = integ = lim if integ > lim else -lim if integ < -lim else integ
        return self.kp * error + self.kd * delta / self.dt + self.ki * integ
