"""Geometric (Mellinger) position controller, as an acceleration command.

It is the paper's third baseline and the fallback that flies any tick where the MPC
fails. The firmware's Mellinger position loop acts in newtons (docs/hardware.md#mellinger); dividing its
gains by the mass gives the same loop expressed as acceleration, which the shared
Mellinger attitude layer then turns into a setpoint exactly as it does for the MPC.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cfknode.flight.settings import ControllerConfig
from cfknode.kernel.vehicle import VehicleConfig


@dataclass(frozen=True)
class GeometricGains:
    kp: np.ndarray  # 1/s^2, per axis
    kd: np.ndarray  # 1/s, per axis

    @classmethod
    def from_config(cls, controller: ControllerConfig, vehicle: VehicleConfig) -> "GeometricGains":
        return cls(
            kp=np.asarray(controller.geometric_kp, dtype=float) / vehicle.mass,
            kd=np.asarray(controller.geometric_kd, dtype=float) / vehicle.mass,
        )


def geometric_acc(
    p: np.ndarray, v: np.ndarray, p_ref: np.ndarray, v_ref: np.ndarray, a_ref: np.ndarray, gains: GeometricGains
) -> np.ndarray:
    """a = a_ref + Kp (p_ref - p) + Kd (v_ref - v): feedforward plus PD on the tracking error."""
    return a_ref + gains.kp * (p_ref - p) + gains.kd * (v_ref - v)
