"""The geometric (SE(3)) baseline of the paper, on the flight stack's geometric position loop."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cfknode.flight.geometric import GeometricGains, geometric_acc
from cfknode.kernel.vehicle import VehicleConfig
from cfknode.models.quadrotor import quat_to_rotation

# Gains found pickled in the authors' offline model (docs/paper-code.md#baselines).
PAPER_POSITION_GAINS = GeometricGains(kp=np.full(3, 20.0), kd=np.full(3, 8.9443))  # 1/s^2, 1/s
_NO_FEEDFORWARD = np.zeros(3)


@dataclass(frozen=True)
class AttitudeGains:
    """The paper's SE(3) attitude gains, 1/s^2 and 1/s (times the inertia: N m/rad, N m s/rad)."""

    kr: tuple[float, float, float] = (1000.0, 1000.0, 50.0)
    kw: tuple[float, float, float] = (63.2456, 63.2456, 16.2635)


class GeometricController:
    """Lee/Mellinger SE(3) control on position and velocity of the reference, yaw 0, no feedforward
    (the paper's trajectory provides none), with the nominal mass; run at the plant rate.

    The position loop is the flight stack's (``geometric_acc``); the attitude loop turns the
    force into moments, since the paper's plant takes (T, M) where a Crazyflie takes RPYT."""

    def __init__(
        self,
        vehicle: VehicleConfig,
        gains: GeometricGains = PAPER_POSITION_GAINS,
        attitude: AttitudeGains = AttitudeGains(),
    ) -> None:
        self.vehicle = vehicle
        self.gains = gains
        self.attitude = attitude
        self._inertia = np.asarray(vehicle.inertia)

    def command(self, x: np.ndarray, p_ref: np.ndarray, v_ref: np.ndarray) -> np.ndarray:
        g = self.attitude
        m = self.vehicle.mass
        force = m * geometric_acc(x[0:3], x[3:6], p_ref, v_ref, _NO_FEEDFORWARD, self.gains)
        force[2] += m * self.vehicle.gravity
        rot = quat_to_rotation(x[6:10])
        thrust = float(force @ rot[:, 2])
        b3 = force / np.linalg.norm(force)
        b2 = np.cross(b3, np.array([1.0, 0.0, 0.0]))
        b2 /= np.linalg.norm(b2)
        rot_des = np.column_stack((np.cross(b2, b3), b2, b3))
        s = 0.5 * (rot_des.T @ rot - rot.T @ rot_des)
        e_r = np.array([s[2, 1], s[0, 2], s[1, 0]])
        w = x[10:13]
        jw = self._inertia * w
        moment = self._inertia * (-np.asarray(g.kr) * e_r - np.asarray(g.kw) * w) + np.cross(w, jw)
        return np.array([thrust, moment[0], moment[1], moment[2]])
