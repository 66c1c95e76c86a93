"""One simulated world for a fleet: N ``SimCrazyflie`` stepped together, plant step by plant step.

Every drone keeps its own firmware, battery, scenario and step observers (its mocap, its
``sim://`` link); the world only advances them in lockstep, one ``dt`` at a time for all, so
that couplings between drones (downwash, sim_backend/downwash.py) see everybody's state at
the same instant. The world is ``Steppable`` (``t``, ``step_to``), like a single simulator.
"""

from __future__ import annotations

import threading
from typing import Sequence

from cfknode.sim_backend.crazyflie import SimCrazyflie
from cfknode.sim_backend.downwash import DownwashVehicle, downwash_forces
from cfknode.sim_backend.settings import DownwashConfig
from cfknode.sim_backend.vehicle import Vehicle


class SimWorld:
    """N simulated Crazyflies sharing one time base (all built with the same ``sim.dt``)."""

    def __init__(self, sims: Sequence[SimCrazyflie], downwash: DownwashConfig | None = None) -> None:
        if not sims:
            raise ValueError("a world needs at least one simulator")
        dts = {s.dt for s in sims}
        if len(dts) != 1:
            raise ValueError(f"all simulators of a world must share sim.dt, got {sorted(dts)}")
        if any(s.steps != 0 for s in sims):
            raise ValueError("a world must be built before its simulators' first step")
        self.sims = tuple(sims)
        self.dt = sims[0].dt
        self.lock = threading.RLock()
        self._downwash = downwash if downwash is not None and downwash.enabled else None
        if self._downwash is not None:
            for sim in self.sims:
                if type(sim.vehicle) is not Vehicle:
                    raise ValueError("downwash needs the plain simulated vehicle (it cannot combine with "
                                     "faults.gusts)")
                sim.vehicle = DownwashVehicle(sim.vehicle_config, sim.sim_config)

    @property
    def t(self) -> float:
        return self.sims[0].t

    def step_to(self, t_target: float) -> None:
        """Advance every drone in ``dt`` steps until ``t >= t_target - 1e-12``."""
        with self.lock:
            sims, dt = self.sims, self.dt
            while sims[0].steps * dt < t_target - 1e-12:
                if self._downwash is not None:
                    forces = downwash_forces([s.vehicle.state_list() for s in sims], self._downwash)
                    for sim, force in zip(sims, forces):
                        sim.vehicle.external_force = force
                t_next = (sims[0].steps + 1) * dt
                for sim in sims:
                    sim.step_to(t_next)


__all__ = ["SimWorld"]
