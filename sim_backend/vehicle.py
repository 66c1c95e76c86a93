"""The simulated Crazyflie's plant: rigid body, four lagged motors, drag, wind and the ground.

State (17): the rigid body of ``cfknode.models.quadrotor`` (p, v, q wxyz, w; 13) followed by
the four motor forces [N]. Each motor force follows its commanded force with a first-order
lag. The whole state is integrated with classical RK4 at a fixed step (``sim.dt``), the
motor commands held over the step (the firmware updates them at 500 Hz), and the
quaternion renormalised after every step.

Geometry (X configuration, firmware legacy mixer numbering: docs/hardware.md#mixer), body FLU:

    m4 front-left (+d, +d)      m1 front-right (+d, -d)
    m3 back-left  (-d, +d)      m2 back-right  (-d, -d)          d = arm_length / sqrt(2)

m1 and m3 spin counter-clockwise seen from above, m2 and m4 clockwise; a rotor's reaction
torque opposes its spin, so Mz = thrust_to_torque * (F2 + F4 - F1 - F3).

The rigid-body derivative is ``models.quadrotor.rigid_body_rhs`` evaluated on plain Python
floats (the ``FLOATS`` backend below): the numpy backend costs ~25 us per call on a single
13-vector, four times per step, which alone would blow the 150 us/step budget; on floats the
same equations take ~1 us.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from cfknode.kernel.vehicle import VehicleConfig
from cfknode.sim_backend.settings import SimConfig
from cfknode.models.quadrotor import Backend, rigid_body_rhs
from cfknode.sim_backend.plant import plant_motor_time_constant
from cfknode.sim_backend.scenario import drag_force

# Lists of Python floats in, lists out: the cheapest way to evaluate the shared model equations
# once per RK4 stage.
FLOATS = Backend(unpack=lambda x, n: x, stack=lambda xs: xs)

CMD_MAX = 65535
# Firmware motors.c: a motor asked for less than THRUST_MIN per motor is switched off (docs/hardware.md#thrust-map).
THRUST_MIN = 0.0128  # N


def command_to_force(cmd: float, thrust_max: float) -> float:
    """Per-motor force [N] the firmware's battery-compensated motor driver produces for ``cmd``."""
    force = min(max(cmd, 0.0), CMD_MAX) / CMD_MAX * thrust_max
    return force if force >= THRUST_MIN else 0.0


def motor_wrench(
    f1: float, f2: float, f3: float, f4: float, half_arm: float, thrust_to_torque: float
) -> tuple[float, float, float, float]:
    """Collective thrust [N] and body moments [N m] of the four motor forces (X layout above)."""
    return (
        f1 + f2 + f3 + f4,
        half_arm * ((f3 + f4) - (f1 + f2)),
        half_arm * ((f2 + f3) - (f1 + f4)),
        thrust_to_torque * ((f2 + f4) - (f1 + f3)),
    )


def level_quaternion(qw: float, qx: float, qy: float, qz: float) -> tuple[float, float, float, float]:
    """The level attitude with the same ZYX yaw as ``q``."""
    yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return (math.cos(0.5 * yaw), 0.0, 0.0, math.sin(0.5 * yaw))


class Vehicle:
    """Rigid body + motors, stepped by ``step(motor_commands, mass)``.

    The ground is the plane z = 0. Resting on it (``on_ground``), the vehicle stays level and
    still while the net vertical force cannot lift it; a step that ends below z = 0 is a
    touchdown: z = 0, velocity and rates zeroed, attitude levelled (yaw kept).
    """

    def __init__(self, vehicle: VehicleConfig, sim: SimConfig) -> None:
        if sim.initial_position[2] < 0.0:
            raise ValueError(f"sim.initial_position z must be >= 0 (the ground), got {sim.initial_position[2]}")
        self.dt = sim.dt
        self._vehicle_thrust_max = vehicle.thrust_max_per_motor
        # The plant's thrust map may differ from the config the firmware and controller believe.
        self._thrust_max = vehicle.thrust_max_per_motor * sim.thrust_map_scale
        self._inertia = tuple(vehicle.inertia)
        self._gravity = vehicle.gravity
        self._half_arm = vehicle.arm_length / math.sqrt(2.0)
        self._kappa = vehicle.thrust_to_torque
        self._tau = plant_motor_time_constant(vehicle, sim)
        if 0.0 < self._tau < 0.5 * sim.dt:
            # RK4's decay factor for the lag stops being monotone past dt/tau ~ 2 (unstable at 2.8).
            key = "vehicle" if sim.motor_time_constant is None else "sim"
            raise ValueError(f"{key}.motor_time_constant {self._tau} s is below sim.dt/2; use 0 for no motor lag")
        self._drag = tuple(sim.drag)
        self._wind = tuple(sim.wind)
        self._has_drag = any(c != 0.0 for c in self._drag)
        # RK4 applied to the linear lag F' = (F_cmd - F)/tau is exactly this polynomial in
        # z = -dt/tau; the ground branch uses it so the motors evolve identically on the ground.
        if self._tau > 0.0:
            z = -self.dt / self._tau
            self._lag_factor = 1.0 + z + z * z / 2.0 + z**3 / 6.0 + z**4 / 24.0
            self._inv_tau = 1.0 / self._tau
        else:
            self._lag_factor = 0.0
            self._inv_tau = 0.0
        px, py, pz = (float(c) for c in sim.initial_position)
        self._x: list[float] = [px, py, pz, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        self.on_ground = pz <= 0.0

    # ----------------------------------------------------------------------------- access
    @property
    def state(self) -> np.ndarray:
        """True rigid-body state (13), a fresh array."""
        return np.array(self._x[:13])

    @property
    def motor_forces(self) -> np.ndarray:
        """Current motor forces [N] (m1..m4), a fresh array."""
        return np.array(self._x[13:])

    @property
    def thrust_scale(self) -> float:
        """True force per command / the vehicle config's, now."""
        return self._thrust_max / self._vehicle_thrust_max

    def set_thrust_scale(self, scale: float) -> None:
        """Change the thrust map (a sagging battery), from the next step on."""
        self._thrust_max = self._vehicle_thrust_max * scale

    def state_list(self) -> list[float]:
        """The full 17-state as a list (hot path: no numpy). Do not mutate."""
        return self._x

    def reset(self, state13: Sequence[float], motor_forces: Sequence[float] = (0.0, 0.0, 0.0, 0.0)) -> None:
        """Place the vehicle (e.g. mid-air with spun-up motors); z <= 0 puts it on the ground, level."""
        x = [float(v) for v in state13] + [float(f) for f in motor_forces]
        if len(x) != 17:
            raise ValueError("reset expects 13 rigid-body states and 4 motor forces")
        norm = math.sqrt(x[6] ** 2 + x[7] ** 2 + x[8] ** 2 + x[9] ** 2)
        x[6:10] = [q / norm for q in x[6:10]]
        on_ground = x[2] <= 0.0
        if on_ground:
            _touch_down(x)
        self._x = x
        self.on_ground = on_ground

    # ----------------------------------------------------------------------------- dynamics
    def derivative(self, x: Sequence[float], mass: float, cmd_forces: Sequence[float]) -> list[float]:
        """d/dt of the 17-state with the commanded motor forces held."""
        f1, f2, f3, f4 = x[13], x[14], x[15], x[16]
        u = motor_wrench(f1, f2, f3, f4, self._half_arm, self._kappa)
        force = drag_force(x[3], x[4], x[5], self._drag, self._wind) if self._has_drag else None
        dx = rigid_body_rhs(x[:13], u, mass, self._inertia, self._gravity, FLOATS, force=force)
        k = self._inv_tau
        dx.extend(((cmd_forces[0] - f1) * k, (cmd_forces[1] - f2) * k, (cmd_forces[2] - f3) * k, (cmd_forces[3] - f4) * k))
        return dx

    def ground_lift(self, thrust: float) -> float:
        """Upward force [N] of motors and air on the vehicle resting on the floor (the wind's drag only)."""
        return thrust + drag_force(0.0, 0.0, 0.0, self._drag, self._wind)[2]

    def step(self, motor_commands: Sequence[float], mass: float) -> None:
        """Advance one ``dt`` with the four motor commands (0..65535) held.

        The state list is replaced, never edited in place, so a reader in another thread
        always sees a whole step.
        """
        fmax = self._thrust_max
        cmd = [command_to_force(c, fmax) for c in motor_commands]
        x = self._x
        if self._tau <= 0.0:
            # No lag configured: the forces jump to their commands at the start of the step.
            x = x[:13] + cmd
        if self.on_ground:
            thrust = x[13] + x[14] + x[15] + x[16]
            if self.ground_lift(thrust) <= mass * self._gravity:
                # The ground holds it: only the motors move.
                a = self._lag_factor
                self._x = x[:13] + [c + (f - c) * a for f, c in zip(x[13:], cmd)]
                return
            self.on_ground = False
        x = self._rk4(x, mass, cmd)
        qn = 1.0 / math.sqrt(x[6] * x[6] + x[7] * x[7] + x[8] * x[8] + x[9] * x[9])
        x[6] *= qn
        x[7] *= qn
        x[8] *= qn
        x[9] *= qn
        if x[2] < 0.0:
            _touch_down(x)
            self.on_ground = True
        self._x = x

    def _rk4(self, x: list[float], mass: float, cmd: list[float]) -> list[float]:
        h = self.dt
        hh = 0.5 * h
        f = self.derivative
        k1 = f(x, mass, cmd)
        k2 = f([a + hh * b for a, b in zip(x, k1)], mass, cmd)
        k3 = f([a + hh * b for a, b in zip(x, k2)], mass, cmd)
        k4 = f([a + h * b for a, b in zip(x, k3)], mass, cmd)
        h6 = h / 6.0
        return [a + h6 * (b1 + 2.0 * (b2 + b3) + b4) for a, b1, b2, b3, b4 in zip(x, k1, k2, k3, k4)]


def _touch_down(x: list[float]) -> None:
    """Rest ``x`` on the ground in place: z = 0, still, level with its yaw kept."""
    x[2] = 0.0
    x[3] = x[4] = x[5] = 0.0
    x[10] = x[11] = x[12] = 0.0
    x[6], x[7], x[8], x[9] = level_quaternion(x[6], x[7], x[8], x[9])
