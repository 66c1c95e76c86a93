"""Another drone's wake is not a heavier vehicle: no mass step is called under it.

A drone passing under another meets its downwash: a downward force a few centimetres wide, crossed in 0.04-0.1 s
at 0.5-1.5 m/s. To the step detectors (step_detect.py, imu_step.py) its onset is a vehicle that became heavier,
and the step's fit (step_fit.py), a lasting change fitted to the few frames after it, put the thrust scale at
its bound (2.5) for a moment while the commands scaled with it: 0.2 m along the line at 1.5 m/s
(docs/history.md#another-drones-wake-is-not-a-mass-step). A wake only ever pushes down, so while another drone
is above within ``radius`` horizontally, and for ``HOLD_S`` after, no step that makes the vehicle heavier is
called. A lighter one (leaving a wake the drone hovered in) still is, and the slow observer takes what the wake
leaves on average.
"""

from __future__ import annotations

import math

import numpy as np

from cfknode.flight.neighbours import NONE_ABOVE

HOLD_S = 0.3  # s after leaving the wake's reach: the detectors' run still holds the wake's surprise
REACH_M = float(NONE_ABOVE[2])  # m: no wake beyond this gap (the neighbour input's "none above")


class WakeGuard:
    """``update`` each tick with the drone's position and the drone above's: whether a heavier step is refused."""

    def __init__(self, radius: float) -> None:
        self.radius = radius
        self.reset()

    def reset(self) -> None:
        self._under_t = -math.inf  # s, the last tick under another drone's wake

    def update(self, t: float, p: np.ndarray | None, above: np.ndarray | None) -> bool:
        """True while ``p`` is under ``above`` (world positions) or was within ``HOLD_S``; False with either unknown."""
        if self.radius > 0.0 and p is not None and above is not None:
            dz = float(above[2]) - float(p[2])
            r = math.hypot(float(above[0]) - float(p[0]), float(above[1]) - float(p[1]))
            if 0.0 < dz < REACH_M and r < self.radius:
                self._under_t = t
        return t - self._under_t < HOLD_S


__all__ = ["HOLD_S", "REACH_M", "WakeGuard"]
