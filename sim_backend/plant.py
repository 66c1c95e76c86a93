"""The simulated plant's departures from the vehicle config: pure functions of the settings.

The controller believes ``vehicle:``; the simulator flies ``vehicle:`` modified by ``sim.``'s
plant keys (motor lag, thrust map, battery sag). These helpers say what the plant really is,
so the plant, the benches and the tests compute it one way.
"""

from __future__ import annotations

from typing import Sequence

from cfknode.kernel.vehicle import VehicleConfig
from cfknode.sim_backend.settings import MassChange, SimConfig

CMD_MAX = 65535


def plant_motor_time_constant(vehicle: VehicleConfig, sim: SimConfig) -> float:
    """The plant's motor thrust lag [s]: ``sim.motor_time_constant``, or the vehicle's when unset."""
    return vehicle.motor_time_constant if sim.motor_time_constant is None else sim.motor_time_constant


def thrust_scale_at(t: float, sim: SimConfig) -> float:
    """True force per command / the vehicle config's, at sim time ``t`` (battery sag included)."""
    if sim.battery_sag_per_s <= 0.0:
        return sim.thrust_map_scale
    return sim.thrust_map_scale * max(1.0 - sim.battery_sag_per_s * t, 0.0)


def heaviest_factor(changes: Sequence[MassChange]) -> float:
    """The largest mass / nominal the scenario reaches (1 when it never changes the mass upward)."""
    return max([1.0, *(c.factor for c in changes)])


def thrust_to_weight(vehicle: VehicleConfig, thrust_scale: float = 1.0, mass_factor: float = 1.0) -> float:
    """Thrust at the RPYT clamp over weight, for a plant thrust scale and a mass factor."""
    thrust = 4.0 * vehicle.thrust_max_per_motor * thrust_scale * vehicle.thrust_cmd_clamp / CMD_MAX
    return thrust / (mass_factor * vehicle.mass * vehicle.gravity)


def thrust_scale_for_thrust_to_weight(target: float, vehicle: VehicleConfig, mass_factor: float = 1.0) -> float:
    """The ``sim.thrust_map_scale`` giving thrust-to-weight ``target`` at the clamp with ``mass_factor``.

    E.g. the 29 g Crazyflie 2.1 at the paper's heaviest step (1.33x) has 1.16 at the 60000 clamp;
    ``thrust_scale_for_thrust_to_weight(1.05, vehicle, 1.33)`` = 0.905 leaves it 1.05.
    """
    if target <= 0.0 or mass_factor <= 0.0:
        raise ValueError(f"thrust-to-weight and mass factor must be > 0, got {target}, {mass_factor}")
    return target / thrust_to_weight(vehicle, 1.0, mass_factor)


__all__ = ["heaviest_factor", "plant_motor_time_constant", "thrust_scale_at", "thrust_scale_for_thrust_to_weight",
           "thrust_to_weight"]
