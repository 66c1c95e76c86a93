"""The pose-source interface every mocap backend implements, and its data types.

A pose source hands over the newest rigid-body pose of the Crazyflie. It never
blocks: blocking SDK calls live in the source's own thread, and the 400 Hz loop
only asks ``latest(now)``. Quaternions are scalar-first ``(w, x, y, z)``, body to world.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class Pose:
    """One mocap frame: ``t`` is when it was sampled (flight clock, s), position in m."""

    t: float
    position: np.ndarray
    quaternion: np.ndarray

    def __post_init__(self) -> None:
        # Read-only float64 copies: a frame is shared by the estimator, the safety
        # layer and the log, and none of them may change it under the others.
        pos = np.array(self.position, dtype=np.float64)
        quat = np.array(self.quaternion, dtype=np.float64)
        if pos.shape != (3,) or quat.shape != (4,):
            raise ValueError(f"Pose needs position (3,) and quaternion (4,), got {pos.shape} and {quat.shape}")
        pos.flags.writeable = False
        quat.flags.writeable = False
        object.__setattr__(self, "t", float(self.t))
        object.__setattr__(self, "position", pos)
        object.__setattr__(self, "quaternion", quat)


@dataclass(frozen=True)
class MocapStats:
    """Counters of a pose source: frames received, frames lost, measured frame rate (Hz)."""

    frames: int
    dropouts: int
    rate_hz: float


@runtime_checkable
class PoseSource(Protocol):
    def latest(self, now: float) -> Pose | None:
        """The newest frame available by ``now`` (None before the first); never blocks."""
        ...

    def stats(self) -> MocapStats:
        ...

    def close(self) -> None:
        ...


class RateMeter:
    """Frame rate over a sliding window of frame times, for ``MocapStats.rate_hz``.

    Counting frames in the last ``window`` seconds (rather than averaging intervals)
    lets the rate fall to zero when frames stop, which is what a pre-flight check needs.
    """

    def __init__(self, window: float = 1.0) -> None:
        if window <= 0:
            raise ValueError("window must be > 0")
        self._window = window
        self._times: deque[float] = deque()
        self._first: float | None = None

    def add(self, t: float) -> None:
        if self._first is None:
            self._first = t
        self._times.append(t)
        self._prune(t)

    def rate(self, now: float) -> float:
        self._prune(now)
        n = len(self._times)
        if self._first is None or n == 0:
            return 0.0
        if now - self._first < self._window:
            # Younger than one window: the mean interval is the best estimate we have.
            span = self._times[-1] - self._times[0]
            return (n - 1) / span if n >= 2 and span > 0 else 0.0
        return n / self._window

    def _prune(self, now: float) -> None:
        cutoff = now - self._window
        times = self._times
        while times and times[0] <= cutoff:
            times.popleft()
