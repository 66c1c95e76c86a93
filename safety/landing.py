"""The supervisor's landing reference: straight down from where the drone is, to the ground.

x and y are held (at a point already clamped into the geofence's soft box, so a drone that
crossed the fence is pulled back inside as it descends); z follows a quintic smootherstep,
whose zero velocity and acceleration at both ends make the descent start from a hover and
end without a bump. ``land_speed`` is the peak descent speed, reached half way: a
smootherstep's peak rate is 15/8 of its mean.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from cfknode.kernel.reference import RefSamples

_PEAK_OVER_MEAN = 1.875
MIN_DURATION_S = 0.5


@dataclass(frozen=True)
class Landing:
    start: np.ndarray  # (3,) m: x, y held; z descends from start[2]
    ground_z: float
    t0: float  # flight time the descent starts
    duration: float

    @classmethod
    def plan(cls, start: np.ndarray, ground_z: float, t0: float, land_speed: float) -> Landing:
        height = max(float(start[2]) - ground_z, 0.0)
        duration = max(_PEAK_OVER_MEAN * height / land_speed, MIN_DURATION_S)
        return cls(np.array(start, dtype=float), float(ground_z), float(t0), duration)

    @property
    def t_end(self) -> float:
        return self.t0 + self.duration

    def advance(self, now: float) -> None:
        """Once per tick: a straight descent is planned once and for all (ordered_landing.py's is not)."""

    def describe(self) -> str:
        return f"in {self.duration:.1f} s"

    def sample(self, t: np.ndarray) -> RefSamples:
        """Reference at times ``t`` (n,); before ``t0`` it holds the start, after the end the ground."""
        n = t.shape[0]
        inv = 1.0 / self.duration
        tau = np.minimum(np.maximum((t - self.t0) * inv, 0.0), 1.0)
        t2 = tau * tau
        one_minus = 1.0 - tau
        s = t2 * tau * (10.0 + tau * (6.0 * tau - 15.0))
        ds = 30.0 * t2 * one_minus * one_minus
        dds = 60.0 * tau * one_minus * (1.0 - 2.0 * tau)
        dz = self.ground_z - self.start[2]
        p = np.empty((n, 3))
        p[:, 0] = self.start[0]
        p[:, 1] = self.start[1]
        p[:, 2] = self.start[2] + dz * s
        v = np.zeros((n, 3))
        a = np.zeros((n, 3))
        v[:, 2] = dz * inv * ds
        a[:, 2] = dz * inv * inv * dds
        return RefSamples(t=t, p=p, v=v, a=a, yaw=np.zeros(n))


# ``(start, ground_z, t0, land_speed)`` -> a landing path: ``sample(t)``, ``t_end``, ``advance(now)``, ``describe()``.
LandingPlanner = Callable[[np.ndarray, float, float, float], Any]
