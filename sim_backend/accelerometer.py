"""The simulated accelerometer: what ``acc.x``, ``acc.y``, ``acc.z`` read on the simulated Crazyflie.

An accelerometer measures the specific force, the non-gravitational acceleration in the body
frame: R^T (a_world + g e_z). At hover it reads (0, 0, 1) g; a vehicle that suddenly weighs half
as much at the same thrust reads about 2 g. The true value comes from the plant's own equations
at the current state (thrust, drag, wind, a gust or a neighbour's downwash); the simulator's
seeded generator adds Gaussian noise per sample (``sim.imu_noise``, m/s^2), so a lockstep flight
reproduces, and a constant offset per axis (``sim.imu_bias``, m/s^2: the sensor's zero-g offset). The reading is in g of ``FIRMWARE_G``, as the firmware logs it.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from cfknode.kernel.imu import FIRMWARE_G

# Independent of the mocap's stream (mocap/simulated.py), so logging the accelerometer or not
# leaves every other random draw of a seeded flight as it was.
_STREAM_KEY = 0x494D55  # "IMU"


def specific_force(state: Sequence[float], world_acc: Sequence[float], gravity: float) -> tuple[float, float, float]:
    """R^T (a_world + g e_z) for ``state``'s attitude (q = state[6:10], w x y z, body to world), m/s^2."""
    qw, qx, qy, qz = state[6], state[7], state[8], state[9]
    ax, ay, az = world_acc[0], world_acc[1], world_acc[2] + gravity
    # Rows of R^T are the columns of R (body axes in world coordinates).
    return (
        (1.0 - 2.0 * (qy * qy + qz * qz)) * ax + 2.0 * (qx * qy + qw * qz) * ay + 2.0 * (qx * qz - qw * qy) * az,
        2.0 * (qx * qy - qw * qz) * ax + (1.0 - 2.0 * (qx * qx + qz * qz)) * ay + 2.0 * (qy * qz + qw * qx) * az,
        2.0 * (qx * qz + qw * qy) * ax + 2.0 * (qy * qz - qw * qx) * ay + (1.0 - 2.0 * (qx * qx + qy * qy)) * az,
    )


class Accelerometer:
    """One simulator's accelerometer; a reading is drawn once per sim time, so acc.x/y/z of one
    log packet (and every link reading at that time) share the sample."""

    def __init__(self, sim: Any) -> None:
        """``sim``: a ``SimCrazyflie`` (its vehicle, mass, time and settings)."""
        self._sim = sim
        self._gravity = float(sim.vehicle_config.gravity)
        self._noise = float(getattr(sim.sim_config, "imu_noise", 0.0))
        self._bias = tuple(float(b) for b in getattr(sim.sim_config, "imu_bias", (0.0, 0.0, 0.0)))
        self._rng = np.random.default_rng(np.random.SeedSequence(sim.sim_config.seed, spawn_key=(_STREAM_KEY,)))
        self._t: float | None = None
        self._reading = (0.0, 0.0, 1.0)
        self.samples = 0

    def true_specific_force(self) -> tuple[float, float, float]:
        """The plant's specific force now, body frame, m/s^2 (no noise)."""
        sim = self._sim
        vehicle = sim.vehicle
        x = vehicle.state_list()
        if vehicle.on_ground:
            acc: Sequence[float] = (0.0, 0.0, 0.0)  # the ground holds it: it reads gravity's reaction
        else:
            acc = vehicle.derivative(x, sim.mass, x[13:17])[3:6]
        return specific_force(x, acc, self._gravity)

    def reading_g(self) -> tuple[float, float, float]:
        """The reading at the simulator's current time, in g (noise drawn once per time)."""
        t = self._sim.t
        if t != self._t:
            f = self.true_specific_force()
            if self._noise > 0.0:
                n = self._rng.standard_normal(3) * self._noise
                f = (f[0] + float(n[0]), f[1] + float(n[1]), f[2] + float(n[2]))
            if any(self._bias):  # the ideal sensor's readings stay the same to the bit
                b = self._bias
                f = (f[0] + b[0], f[1] + b[1], f[2] + b[2])
            self._reading = (f[0] / FIRMWARE_G, f[1] / FIRMWARE_G, f[2] / FIRMWARE_G)
            self._t = t
            self.samples += 1
        return self._reading


__all__ = ["Accelerometer", "specific_force"]
