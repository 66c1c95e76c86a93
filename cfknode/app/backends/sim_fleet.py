"""The simulator backend for a fleet: N simulated Crazyflies in one world, each behind the real cflib path.

Each drone is a ``SimCrazyflie`` registered at its own ``sim://N`` URI and reached through its
own ``CflibRadio`` (the stock cflib ``Crazyflie`` and ``Commander``), with its own simulated
mocap. The drones share one ``SimWorld`` (stepped plant step by plant step, with downwash when
``sim.downwash.enabled``) and one lockstep ``FleetClock``: every drone's flight loop gets a
member clock, and the world steps only when all of them wait for the next tick.

Injected faults (``faults:``) act on the first drone only, so the fleet's fault policy
(``fleet.on_fault``) can be exercised; the others fly fault-free.
"""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Any, Iterator, Sequence


from cfknode.app.backends.radio import CflibRadio
from cfknode.app.backends.sim import SimulatorBackend, sim_radio, vehicle_after
from cfknode.app.config import Config, ConfigError
from cfknode.kernel.fleet_clock import FleetClock, MemberClock
from cfknode.mocap.simulated import SimulatedMocap
from cfknode.sim_backend.crazyflie import SimCrazyflie
from cfknode.sim_backend.faults import SimFaults, install_faults
from cfknode.sim_backend.link_driver import register_simulator, unregister_simulator
from cfknode.sim_backend.world import SimWorld


def fault_free(faults: Any) -> Any:
    """``faults`` with nothing injected: the fleet's drones after the first fly fault-free."""
    return dataclasses.replace(faults, mocap_outages=(), radio_outages=(), solver_failures=(), nan_model_at=-1.0,
                               battery_drop_at=-1.0, gusts=(), sigint_at=())


class FleetDrone(SimulatorBackend):
    """One drone of the fleet as its flight sees it: the simulator backend on a member clock of the world."""

    def __init__(self, name: str, cfg: Config, sim: SimCrazyflie, faults: SimFaults, mocap: SimulatedMocap,
                 clock: MemberClock, radio: CflibRadio) -> None:
        super().__init__(cfg, sim, faults, mocap, clock, radio)  # type: ignore[arg-type]
        self.name = name

    def after_handback(self) -> dict[str, Any]:
        # The world (not this drone alone) runs on past the hand-back, so every drone stays in step.
        return {"firmware_after_shutdown": self.sim.firmware.supervisor_state,
                "vehicle_after_shutdown": vehicle_after(self.sim)}


class FleetSimBackend:
    """The fleet's world, clock and drones; open it with ``FleetSimBackend.open(names, configs)``."""

    def __init__(self, world: SimWorld, clock: FleetClock, drones: Sequence[FleetDrone]) -> None:
        self.world, self.clock, self.drones = world, clock, tuple(drones)

    @classmethod
    @contextlib.contextmanager
    def open(cls, names: Sequence[str], configs: Sequence[Config]) -> Iterator["FleetSimBackend"]:
        """``configs[i]``: drone i's flight config (its ``radio.uri``, ``sim.initial_position``, seed)."""
        if any(c.sim.realtime for c in configs):
            raise ConfigError("config key 'sim.realtime': a fleet flies in lockstep only")
        uris = [c.radio.uri for c in configs]
        if len(set(uris)) != len(uris):
            raise ConfigError(f"fleet drones need distinct radio URIs, got {uris}")
        sims = [SimCrazyflie(c.vehicle, c.sim) for c in configs]
        no_faults = fault_free(configs[0].faults)
        faults = [install_faults(sim, c.faults if i == 0 else no_faults) for i, (sim, c) in enumerate(zip(sims, configs))]
        try:
            world = SimWorld(sims, configs[0].sim.downwash)
        except ValueError as exc:
            raise ConfigError(f"config key 'sim.downwash': {exc}") from None
        fleet_clock = FleetClock(world)
        mocaps = [SimulatedMocap.from_config(s, c.sim, outages=f.mocap_outages) for s, c, f in zip(sims, configs, faults)]
        registered: list[str] = []
        radios: list[CflibRadio] = []
        try:
            for sim, c in zip(sims, configs):
                register_simulator(c.radio.uri, sim)
                registered.append(c.radio.uri)
            drones = []
            for name, sim, c, f, mocap in zip(names, sims, configs, faults, mocaps):
                member = fleet_clock.member()
                radio = sim_radio(c, member.now, world.step_to)  # as a single flight's, its accelerometer log too
                radios.append(radio)
                radio.connect()
                drones.append(FleetDrone(name, c, sim, f, mocap, member, radio))
            yield cls(world, fleet_clock, drones)
        finally:
            for radio in radios:
                radio.shutdown()
            for mocap in mocaps:
                mocap.close()
            for uri in registered:
                unregister_simulator(uri)

    def settle_after_handback(self) -> dict[str, str]:
        """Each drone's firmware state once the hand-back settled (the world runs on 2.5 s)."""
        self.world.step_to(self.world.t + 2.5)
        return {d.name: d.sim.firmware.supervisor_state for d in self.drones}


__all__ = ["FleetDrone", "FleetSimBackend", "fault_free"]
