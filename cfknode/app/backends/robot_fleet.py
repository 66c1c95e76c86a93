"""The hardware backend for a fleet of named robots (``cfknode fly --robots cf1,cf2``).

Every robot gets what a single ``--backend cf`` flight gets (backends/crazyflie.py): its own
cflib link at its URI from the robots file, its firmware parameters, its pre-flight checks, and
its vehicle numbers in its flight config. The lab's one mocap system is opened once
(``MocapHub``): one connection and one reader thread, each frame handed to every robot's
source by rigid-body name, and from there to that robot's radio as extposes. When every robot
is checked, one wall clock starts for all of them.

Robots whose URIs are ``sim://N`` fly the simulator through exactly this code: each is a
``SimCrazyflie`` behind cflib's ``sim://`` driver, all in one ``SimWorld`` stepped against the
wall clock (so downwash couples them when ``sim.downwash.enabled``), and one simulated
``motioncapture`` client serves every body. A fleet is all real or all simulated.
"""

from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass
from typing import Any, Iterator, Sequence

from cfknode.app.backends.crazyflie import CrazyflieBackend, HardwareBackend, connect_robot, flight_config
from cfknode.app.backends.robots import Robot
from cfknode.app.backends.sim_mocap import SimulatedMotionCaptureClient
from cfknode.app.config import Config, ConfigError
from cfknode.kernel.clock import WallClock
from cfknode.mocap.motioncapture_source import Connector
from cfknode.mocap.shared_source import MocapHub


def robot_config(cfg: Config, robot: Robot) -> Config:
    """Robot ``robot``'s flight config: its name (messages, e-stop), vehicle numbers, URI and battery limits."""
    named = dataclasses.replace(cfg, hardware=dataclasses.replace(cfg.hardware, robot=robot.name))
    return flight_config(named, robot)


def robot_configs(cfg: Config, robots: Sequence[Robot]) -> list[Config]:
    """Each robot's flight config (``robot_config``) as a drone of a fleet of them: ``fleet.size`` is the number of
    robots, so its learning sees the fleet (the neighbour input, wake networks), and a drone whose networks learn a
    wake (``fleet.wake_only``) takes the wake's settings (cfknode/app/fleet/wake_below.py)."""
    from cfknode.app.fleet.wake_below import wake_below_configs

    configs = [robot_config(cfg, r) for r in robots]
    configs = [dataclasses.replace(c, fleet=dataclasses.replace(c.fleet, size=len(robots))) for c in configs]
    return wake_below_configs(cfg, configs, None)


@dataclass(frozen=True)
class SimulatedLab:
    sims: tuple[Any, ...]  # SimCrazyflie per robot, in the robots' order
    connect: Connector  # a motioncapture.connect stand-in serving every robot's body
    clock: WallClock  # the world's own wall clock (the drones' time, not the flight's)


@contextlib.contextmanager
def simulated_lab(cfg: Config, robots: Sequence[Robot]) -> Iterator[SimulatedLab]:
    """Simulated Crazyflies at the robots' ``sim://`` URIs in one world stepped in real time.

    The physics is ``cfg.vehicle`` and ``cfg.sim`` (as for one ``sim://`` robot, the flight
    stack believes the robots file); robot i starts at its ``initial_position`` with seed
    ``sim.seed + i``. Mocap noise, latency and dropouts come from ``cfg.sim``.
    """
    from cfknode.sim_backend.crazyflie import SimCrazyflie
    from cfknode.sim_backend.link_driver import register_simulator, unregister_simulator
    from cfknode.sim_backend.realtime import RealtimeStepper
    from cfknode.sim_backend.world import SimWorld

    sims = [SimCrazyflie(cfg.vehicle, dataclasses.replace(cfg.sim, initial_position=r.initial_position,
                                                          realtime=True, seed=cfg.sim.seed + i))
            for i, r in enumerate(robots)]
    try:
        world = SimWorld(sims, cfg.sim.downwash)
    except ValueError as exc:
        raise ConfigError(f"config key 'sim.downwash': {exc}") from None
    registered: list[str] = []
    served: list[SimulatedMotionCaptureClient] = []
    stepper = None
    try:
        for robot, sim in zip(robots, sims):
            register_simulator(robot.uri, sim)
            registered.append(robot.uri)
        clock = WallClock()
        stepper = RealtimeStepper(world, clock.now).start()

        def connect(mocap_type: str, mocap_cfg: dict[str, str]) -> SimulatedMotionCaptureClient:
            s = cfg.sim
            client = SimulatedMotionCaptureClient(
                {r.name: sim for r, sim in zip(robots, sims)}, rate_hz=cfg.hardware.mocap_rate_hz,
                position_noise=s.mocap_position_noise, attitude_noise=s.mocap_attitude_noise,
                latency=s.mocap_latency, dropout_prob=s.mocap_dropout_prob, seed=s.seed,
                frame_time=clock.monotonic)  # the world's time is this clock's (the stepper's)
            served.append(client)
            return client

        yield SimulatedLab(sims=tuple(sims), connect=connect, clock=clock)
    finally:
        if stepper is not None:
            stepper.stop()
        for client in served:
            client.close()
        for uri in registered:
            unregister_simulator(uri)


class RobotFleetBackend:
    """The fleet's drones (each a ``CrazyflieBackend`` on the one flight clock); open with ``RobotFleetBackend.open``."""

    def __init__(self, drones: Sequence[CrazyflieBackend], clock: WallClock, hub: MocapHub) -> None:
        self.drones, self.clock, self.hub = tuple(drones), clock, hub

    @classmethod
    @contextlib.contextmanager
    def open(cls, cfg: Config, robots: Sequence[Robot], console: Any = None) -> Iterator["RobotFleetBackend"]:
        """Connect the mocap once, then each robot in turn (radio, extposes, pre-flight checks),
        then start the clock. Raises ``ConfigError`` or one of ``HARDWARE_ERRORS``; on the way
        out (any way out) every connected robot is handed back and the mocap closed."""
        simulated = [r.uri.startswith("sim://") for r in robots]
        if any(simulated) and not all(simulated):
            raise ConfigError("a fleet is all real robots or all simulated (sim://) ones, not both: "
                              + ", ".join(f"{r.name} {r.uri}" for r in robots))
        hw = cfg.hardware
        with contextlib.ExitStack() as stack:
            connect: Connector | None = None
            sims: Sequence[Any] = [None] * len(robots)
            mocap_type = hw.mocap_type
            if all(simulated):
                lab = stack.enter_context(simulated_lab(cfg, robots))
                # The simulator stands in for the mocap system, through the same reader thread.
                connect, sims, mocap_type = lab.connect, lab.sims, "mock"
            hub = MocapHub.open(mocap_type, hw.mocap_host, [r.name for r in robots], timeout=hw.mocap_connect_timeout,
                                connect=connect, expected_rate_hz=hw.mocap_rate_hz,
                                mock_bodies={r.name: (*r.initial_position, 1.0, 0.0, 0.0, 0.0) for r in robots})
            stack.callback(hub.close)
            links = [stack.enter_context(connect_robot(cfg, robot, hub.source(robot.name), console=console))
                     for robot in robots]
            clock = WallClock()
            drones = []
            for robot, config, link, sim in zip(robots, robot_configs(cfg, robots), links, sims):
                source = hub.source(robot.name)
                source.set_time_base(clock.now)
                link.radio.set_clock(clock.now)
                drones.append(CrazyflieBackend(HardwareBackend(
                    robot=robot, config=config, mocap=source, radio=link.radio, clock=clock,
                    preflight=link.preflight, start_position=link.start_position,
                    truth=(lambda s=sim: s.state) if sim is not None else None, sim=sim)))
            yield cls(drones, clock, hub)


__all__ = ["RobotFleetBackend", "SimulatedLab", "robot_config", "robot_configs", "simulated_lab"]
