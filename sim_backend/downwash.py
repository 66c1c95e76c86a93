"""Downwash between simulated drones: a drone below another is pushed down by its wake.

A deliberately simple, documented model (docs/fleet.md#downwash), not a fluid simulation:

    F_z = -peak_fraction * T_upper * max(0, 1 - dz / height) * exp(-(r / radius)^2)     for dz > 0

with ``dz`` the upper drone's height above the lower one, ``r`` their horizontal distance and
``T_upper`` the upper drone's current collective thrust (a landed drone, motors off, makes no wake).
Horizontal components are neglected.

Why these shapes and numbers: Crazyswarm (Preiss et al., "Crazyswarm: A large nano-quadcopter
swarm", ICRA 2017) keeps Crazyflies apart with an ellipsoid of 0.12 m horizontal and 0.3 m
vertical radius because of downwash, i.e. the wake is narrow (rotor-disk / airframe scale)
and long; Neural-Swarm (Shi et al., "Neural-Swarm: Decentralized close-proximity multirotor
control using learned interactions", ICRA 2020) measured the interaction on stacked Crazyflie
2.0s as a downward force well within their thrust margin that still degrades height tracking
noticeably up to about half a metre of vertical separation. The defaults (15 % of the upper
thrust right below, half of that at 0.5 m, a 0.1 m Gaussian radius) sit in that range; they
are configuration (``sim.downwash``), not measurements of this simulator.

The realistic plant (``sim.aero: realistic``) has its own, measured wake instead
(``measured_wake``: Neural-Swarm2's learned interaction model, docs/hardware.md#simulator).
"""

from __future__ import annotations

import math
from functools import partial
from typing import Callable, Sequence

from cfknode.kernel.vehicle import VehicleConfig
from cfknode.sim_backend.scenario import drag_force
from cfknode.sim_backend.aero import measured_downwash_force_z
from cfknode.sim_backend.settings import AeroTerms, DownwashConfig, SimConfig
from cfknode.sim_backend.vehicle import FLOATS, Vehicle, motor_wrench
from cfknode.models.quadrotor import rigid_body_rhs

_NO_FORCE = (0.0, 0.0, 0.0)
WakeLaw = Callable[[Sequence[float], Sequence[float], float], float]


def downwash_force_z(lower: Sequence[float], upper: Sequence[float], upper_thrust: float,
                     cfg: DownwashConfig) -> float:
    """Vertical force [N] (<= 0) the wake of the drone at ``upper`` puts on the drone at ``lower``."""
    dz = upper[2] - lower[2]
    if dz <= 0.0 or dz >= cfg.height or upper_thrust <= 0.0:
        return 0.0
    dx, dy = upper[0] - lower[0], upper[1] - lower[1]
    r2 = dx * dx + dy * dy
    radial = math.exp(-r2 / (cfg.radius * cfg.radius))
    return -cfg.peak_fraction * upper_thrust * (1.0 - dz / cfg.height) * radial


def downwash_forces(states: Sequence[Sequence[float]],
                    cfg: DownwashConfig | WakeLaw) -> list[tuple[float, float, float]]:
    """The world force on each drone from all the others' wakes; ``states`` are 17-states
    (p, v, q, w, motor forces) as ``Vehicle.state_list`` returns them. ``cfg``: this module's
    model's settings, or any wake law ``(lower, upper, upper_thrust) -> F_z`` (the realistic
    plant's: ``measured_wake``)."""
    law = cfg if callable(cfg) else partial(downwash_force_z, cfg=cfg)
    thrusts = [x[13] + x[14] + x[15] + x[16] for x in states]
    out = []
    for i, xi in enumerate(states):
        fz = 0.0
        for j, xj in enumerate(states):
            if j != i:
                fz += law(xi, xj, thrusts[j])
        out.append((0.0, 0.0, fz) if fz != 0.0 else _NO_FORCE)
    return out


def measured_wake(terms: AeroTerms) -> WakeLaw:
    """The realistic plant's wake law (Neural-Swarm2's strength and width, sim_backend/aero.py)."""
    return partial(measured_downwash_force_z, scale=terms.downwash, width=terms.downwash_width)


class DownwashVehicle(Vehicle):
    """The plant with an external world force (``external_force``, N) held over each step."""

    def __init__(self, vehicle: VehicleConfig, sim: SimConfig) -> None:
        super().__init__(vehicle, sim)
        self.external_force: tuple[float, float, float] = _NO_FORCE

    def derivative(self, x: Sequence[float], mass: float, cmd_forces: Sequence[float]) -> list[float]:
        ext = self.external_force
        if ext is _NO_FORCE:
            return super().derivative(x, mass, cmd_forces)
        f1, f2, f3, f4 = x[13], x[14], x[15], x[16]
        u = motor_wrench(f1, f2, f3, f4, self._half_arm, self._kappa)
        if self._has_drag:
            d = drag_force(x[3], x[4], x[5], self._drag, self._wind)
            force = (d[0] + ext[0], d[1] + ext[1], d[2] + ext[2])
        else:
            force = ext
        dx = rigid_body_rhs(x[:13], u, mass, self._inertia, self._gravity, FLOATS, force=force)
        k = self._inv_tau
        dx.extend(((cmd_forces[0] - f1) * k, (cmd_forces[1] - f2) * k, (cmd_forces[2] - f3) * k,
                   (cmd_forces[3] - f4) * k))
        return dx


__all__ = ["DownwashVehicle", "WakeLaw", "downwash_force_z", "downwash_forces", "measured_wake"]
