"""The paper's Crazyflie (flightsim / RotorPy ``crazyflie`` parameters) in the flight stack's terms.

The airframe is a ``VehicleConfig`` like any robot's; what the flight stack does not model, the
rotor-speed law force = k_t * speed^2 with its speed limits, is ``PaperRotors``. The paper's
vehicle differs from the flight stack's robots (a 0.575 N collective limit, instantaneous
motors, no RPYT thrust clamp), so it is its own instance, built from the rotor law.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cfknode.kernel.vehicle import VehicleConfig


@dataclass(frozen=True)
class PaperRotors:
    """flightsim's rotors: force k_t w^2 and drag torque k_d w^2 at speed w in [rotor_min, rotor_max]."""

    rotor_min: float = 0.0  # rad/s
    rotor_max: float = 2500.0  # rad/s
    k_t: float = 2.3e-8  # N / (rad/s)^2
    k_d: float = 7.8e-11  # N m / (rad/s)^2
    trim_rotor_speed: float = 1790.0  # rad/s: seeds the original's negative-force fallback

    @property
    def force_max(self) -> float:
        """One rotor at full speed, N."""
        return self.k_t * self.rotor_max**2


PAPER_ROTORS = PaperRotors()


def paper_vehicle(
    rotors: PaperRotors = PAPER_ROTORS,
    *,
    mass: float = 0.03,
    inertia: tuple[float, float, float] = (1.43e-5, 1.43e-5, 2.89e-5),
    arm_length: float = 0.046,
    gravity: float = 9.81,
) -> VehicleConfig:
    """The paper's airframe as a ``VehicleConfig``: thrust limit and yaw moment from ``rotors``."""
    return VehicleConfig(
        mass=mass,  # kg
        inertia=inertia,  # kg m^2
        arm_length=arm_length,  # m
        thrust_max_per_motor=rotors.force_max,  # 4 x 0.14375 = 0.575 N collective
        thrust_cmd_clamp=65535,  # no RPYT interface: the whole rotor range is usable
        thrust_to_torque=rotors.k_d / rotors.k_t,
        motor_time_constant=0.0,  # the paper's motors are instantaneous
        gravity=gravity,
    )


PAPER_VEHICLE = paper_vehicle()


def plus_mixer(vehicle: VehicleConfig) -> np.ndarray:
    """(T, Mx, My, Mz) = mixer @ rotor forces, "+" layout (the paper's)."""
    arm, k = vehicle.arm_length, vehicle.thrust_to_torque
    return np.array([[1.0, 1.0, 1.0, 1.0], [0.0, arm, 0.0, -arm], [-arm, 0.0, arm, 0.0], [k, -k, k, -k]])
