"""What a flight needs of the world it flies in: the ``Backend`` protocol.

Exactly two implementations: ``SimulatorBackend`` (backends/sim.py: the simulated Crazyflie
behind cflib's ``sim://`` driver, simulated mocap, lockstep or wall clock, injected faults) and
``CrazyflieBackend`` (backends/crazyflie.py: a robot from the robots file over a Crazyradio,
its mocap over ``motioncapture``, pre-flight checks; a ``sim://`` robot is this backend
pointed at the simulator). The mission sees only this protocol.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from cfknode.kernel.clock import Clock
from cfknode.kernel.imu import ImuSource
from cfknode.kernel.link import LinkStatus
from cfknode.mocap.source import PoseSource


class Backend(Protocol):
    config: Any  # the flight's Config (on hardware: with the robot's mass, limits and URI)
    clock: Clock
    mocap: PoseSource
    radio: Any  # a CflibRadio: connect, send, shutdown (the hand-back), stats
    start_position: np.ndarray  # where the take-off starts, m
    events: tuple[dict[str, Any], ...]  # logged before take-off (pre-flight checks)
    imu: ImuSource | None  # the vehicle's accelerometer samples (radio.imu_log), None without

    def truth(self) -> np.ndarray | None:
        """The true 13-state in simulation (logs, MSE), None on hardware."""
        ...

    def true_mass(self) -> float | None:
        """The simulator's true mass (the oracle reads it), None on hardware."""
        ...

    def battery_voltage(self) -> float | None: ...

    def link_status(self, now: float) -> LinkStatus: ...

    def wrap_solver(self, solver: Any) -> Any:
        """The MPC as the flight should see it (the simulator injects solver faults here)."""
        ...

    def fault_observers(self, model: Any) -> list[Any]:
        """Tick observers that inject faults (simulator only)."""
        ...

    def after_handback(self) -> dict[str, Any]:
        """Summary extras once the drone is handed back (firmware state, pre-flight report)."""
        ...
