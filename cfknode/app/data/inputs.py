"""The commanded world acceleration u (v' = u for the nominal model) from what a dataset recorded.

Three kinds of input, each with the attitude that points its thrust:
- motor speeds w_i (rad/s) and a thrust coefficient k_f: T = k_f sum w_i^2, along the measured body z;
- a collective thrust T (N), along the measured body z;
- the RPYT command cflib sends: roll and pitch (deg, right-handed ZYX) and a 0-65535 thrust through
  the vehicle's thrust map, along the commanded attitude (yaw from the measured quaternion).
Then u = R e3 T / m - g e3: pure functions, vectorised over samples.
"""

from __future__ import annotations

import numpy as np


def body_z(q_wxyz: np.ndarray) -> np.ndarray:
    """The body z axis in the world frame, (n, 3), from scalar-first unit quaternions (n, 4)."""
    w, x, y, z = (q_wxyz[:, k] for k in range(4))
    return np.stack((2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)), axis=1)


def yaw_of(q_wxyz: np.ndarray) -> np.ndarray:
    w, x, y, z = (q_wxyz[:, k] for k in range(4))
    return np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def body_z_from_euler(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Body z in the world for ZYX Euler angles (rad), as the firmware composes its attitude setpoint."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    return np.stack((cy * sp * cr + sy * sr, sy * sp * cr - cy * sr, cp * cr), axis=1)


def acceleration(direction: np.ndarray, thrust_n: np.ndarray, mass: float, gravity: float) -> np.ndarray:
    """u = direction T / m - g e3, (n, 3) m/s^2."""
    u = direction * (thrust_n / mass)[:, None]
    u[:, 2] -= gravity
    return u


def motor_thrust(speeds: np.ndarray, coefficient: float) -> np.ndarray:
    """Collective thrust (N) from motor speeds (n, 4) in rad/s: k_f sum w^2."""
    return coefficient * np.sum(speeds * speeds, axis=1)


def pwm_thrust(pwm: np.ndarray, newton_per_cmd: float) -> np.ndarray:
    """Collective thrust (N) from the 0-65535 thrust command, by the vehicle's linear map (docs/hardware.md)."""
    return np.maximum(pwm, 0.0) * newton_per_cmd
