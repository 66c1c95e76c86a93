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
from cfknode.sim_backend.aero_vehicle import AeroVehicle
from cfknode.sim_backend.downwash import DownwashVehicle, WakeLaw, downwash_forces, measured_wake
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
        self._downwash = _wake_law(self.sims, downwash)
        if self._downwash is not None and not all(isinstance(s.vehicle, AeroVehicle) for s in self.sims):
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


def _wake_law(sims: Sequence[SimCrazyflie], downwash: DownwashConfig | None) -> DownwashConfig | WakeLaw | None:
    """What pushes a drone below another: ``sim.downwash``'s model on the ideal plant (when enabled),
    the measured wake on the realistic one (unless its scale is 0), else nothing."""
    kinds = {s.sim_config.aero for s in sims}
    if len(kinds) != 1:
        raise ValueError(f"all simulators of a world must share sim.aero, got {sorted(kinds)}")
    enabled = downwash is not None and downwash.enabled
    if kinds == {"ideal"}:
        return downwash if enabled else None
    if enabled:
        raise ValueError("sim.downwash is the ideal plant's wake; the realistic plant has its own "
                         "(sim.aero_terms.downwash)")
    terms = sims[0].sim_config.aero_terms
    return measured_wake(terms) if terms.downwash > 0.0 else None


__all__ = ["SimWorld"]
