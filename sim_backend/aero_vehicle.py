"""The realistic plant (``sim.aero: realistic``): the ideal ``Vehicle`` plus the air around it.

On top of the rigid body, the lagged motors and ``sim.drag``, every derivative adds
(sim_backend/aero.py, docs/hardware.md#simulator):

- rotor drag in the rotor plane and the inflow thrust loss along the rotor axis, on the
  velocity relative to the air (``sim.wind``, or a gust's), proportional to the rotor speeds;
- ground effect near the floor z = 0;
- ``external_force``, the wake of drones above (set by ``SimWorld`` before each step);
- the fast unmodelled force (sim_backend/fast_force.py), drawn once per step and held over it.

Everything else (motor lag, touchdown, the on-ground branch, RK4) is the ideal plant's.
"""

from __future__ import annotations

import math
from typing import Sequence

from cfknode.kernel.vehicle import VehicleConfig
from cfknode.models.quadrotor import rigid_body_rhs
from cfknode.sim_backend.aero import ground_effect_fraction, rotor_and_ground_force, rotor_speed_ratio
from cfknode.sim_backend.fast_force import FastForce
from cfknode.sim_backend.scenario import drag_force, wind_at
from cfknode.sim_backend.settings import Gust, SimConfig
from cfknode.sim_backend.vehicle import FLOATS, Vehicle, motor_wrench

_NO_FORCE = (0.0, 0.0, 0.0)


class AeroVehicle(Vehicle):
    """The plant with rotor drag, inflow, ground effect, a world force and the fast force.

    ``gusts`` replace the wind while they blow (``faults.gusts``), as ``GustVehicle`` does for
    the ideal plant; here the rotors feel them too.
    """

    def __init__(self, vehicle: VehicleConfig, sim: SimConfig, gusts: Sequence[Gust] = ()) -> None:
        super().__init__(vehicle, sim)
        terms = sim.aero_terms
        mass = vehicle.mass
        # Coefficients per unit of nominal mass at hover rotor speed, as forces [N per m/s].
        self._k_drag = terms.rotor_drag * mass
        self._k_inflow = terms.inflow * mass
        self._hover_force = mass * vehicle.gravity / 4.0
        self._rotor_speed = 0.0  # summed rotor speeds / at hover, for the current step
        self._ground_scale = terms.ground_effect
        self._fast_mass = mass
        self._fast = None
        if terms.fast_rms > 0.0 or terms.fast_rms_per_speed2 > 0.0:
            self._fast = FastForce(sim.seed, sim.dt, terms.fast_band_hz, terms.fast_rms, terms.fast_rms_per_speed2)
        self._calm = tuple(sim.wind)
        self._gusts = tuple(gusts)
        self._steps = 0
        self.external_force: tuple[float, float, float] = _NO_FORCE
        self.fast_force: tuple[float, float, float] = _NO_FORCE  # N, held over the current step
        self._held = _NO_FORCE  # N, the two above summed for the current step

    def air_force(self, x: Sequence[float]) -> tuple[float, float, float]:
        """World force [N] of the rotors' drag and inflow, the ground effect, ``sim.drag``, the world
        force and the fast force on the 17-state ``x``."""
        wind = self._wind
        speed = self._rotor_speed
        rx, ry, rz = rotor_and_ground_force(x, wind, self._k_drag * speed, self._k_inflow * speed,
                                            self._ground_scale)
        hx, hy, hz = self._held
        fx, fy, fz = rx + hx, ry + hy, rz + hz
        if self._has_drag:
            d = drag_force(x[3], x[4], x[5], self._drag, wind)
            fx, fy, fz = fx + d[0], fy + d[1], fz + d[2]
        return fx, fy, fz

    def derivative(self, x: Sequence[float], mass: float, cmd_forces: Sequence[float]) -> list[float]:
        f1, f2, f3, f4 = x[13], x[14], x[15], x[16]
        u = motor_wrench(f1, f2, f3, f4, self._half_arm, self._kappa)
        dx = rigid_body_rhs(x[:13], u, mass, self._inertia, self._gravity, FLOATS, force=self.air_force(x))
        k = self._inv_tau
        dx.extend(((cmd_forces[0] - f1) * k, (cmd_forces[1] - f2) * k, (cmd_forces[2] - f3) * k,
                   (cmd_forces[3] - f4) * k))
        return dx

    def reset(self, state13: Sequence[float], motor_forces: Sequence[float] = (0.0, 0.0, 0.0, 0.0)) -> None:
        super().reset(state13, motor_forces)
        self._hold_rotor_speed()

    def _hold_rotor_speed(self) -> None:
        # The rotor speeds, held over a step like the fast force: the motors lag by ~8 steps.
        x = self._x
        self._rotor_speed = rotor_speed_ratio(x[13], x[14], x[15], x[16], self._hover_force)

    def ground_lift(self, thrust: float) -> float:
        """Upward force [N] of motors and air on the vehicle resting on the floor (the ground effect's most)."""
        return thrust * (1.0 + ground_effect_fraction(0.0, self._ground_scale)) + super().ground_lift(0.0)

    def step(self, motor_commands: Sequence[float], mass: float) -> None:
        # Called once per plant step (SimCrazyflie.step_to), so the step count is sim time.
        t = self._steps * self.dt
        self._steps += 1
        if self._gusts:
            self._wind = wind_at(t, self._calm, self._gusts)
        self._hold_rotor_speed()
        x = self._x
        if self._fast is not None:
            w = self._wind
            airspeed = math.sqrt((x[3] - w[0]) ** 2 + (x[4] - w[1]) ** 2 + (x[5] - w[2]) ** 2)
            ax, ay, az = self._fast.step(airspeed)
            m = self._fast_mass
            self.fast_force = (ax * m, ay * m, az * m)
        (ex, ey, ez), (sx, sy, sz) = self.external_force, self.fast_force
        self._held = (ex + sx, ey + sy, ez + sz)
        super().step(motor_commands, mass)


def make_vehicle(vehicle: VehicleConfig, sim: SimConfig) -> Vehicle:
    """The plant ``sim.aero`` selects: the ideal ``Vehicle`` or the realistic ``AeroVehicle``."""
    if sim.aero == "realistic":
        return AeroVehicle(vehicle, sim)
    if sim.aero == "ideal":
        return Vehicle(vehicle, sim)
    raise ValueError(f"sim.aero must be ideal or realistic, got {sim.aero!r}")


__all__ = ["AeroVehicle", "make_vehicle"]
