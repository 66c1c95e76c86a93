"""Which motor lag the vehicle has: a bank of first-order thrust lags, the one that predicts the climb best wins.

The fast adaptation layer compares the vehicle with the thrust that acts now, the thrust sent through the
motors' lag. A lag wrong by 10x (a 150 ms motor where 15 ms was configured) makes every thrust change look
like a disturbance, and the observer rings on it. So each candidate lag filters the sent thrust, predicts
the vertical velocity change from one mocap frame to the next, and keeps a running mean square of its
miss; the candidate with the smallest (by a margin, so the choice does not flicker) is the one used.

The candidates' state is lists of floats, not arrays: a handful of numbers updated every tick, where numpy's
per-call cost (~1 us an operation with a scalar) was the work; the arithmetic, element by element in the same
order, gives the same numbers.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

SWITCH_MARGIN = 0.8  # a candidate takes over when its mean square miss is below this fraction of the current's
MISS_FRAMES = 200  # mocap frames the mean square averages over (2 s at 100 Hz)


class ThrustLagBank:
    def __init__(self, lags_s: Sequence[float], configured_s: float, rate_hz: float) -> None:
        lags = sorted({float(x) for x in lags_s} | {float(configured_s)})
        self.lags = np.array(lags)
        self._alpha = [1.0 - math.exp(-1.0 / (rate_hz * x)) if x > 0.0 else 1.0 for x in lags]
        self._dt = 1.0 / rate_hz
        self.choice = int(lags.index(float(configured_s)))
        self.switches = 0
        self.reset()

    def reset(self) -> None:
        n = len(self.lags)
        self._acting: list[float] | None = None  # N, each candidate's acting thrust
        self._miss = [0.0] * n  # m/s, each candidate's unexplained velocity change this frame
        self._ms = [0.0] * n  # (m/s)^2, running mean square of the frame misses
        self._frames = 0
        self._v_prev: float | None = None
        self._imu_ms = [0.0] * n  # (m/s^2)^2, running mean square of the accelerometer misses
        self._imu_samples = 0

    @property
    def lag_s(self) -> float:
        return float(self.lags[self.choice])

    def acting(self) -> float | None:
        """N, the thrust acting now under the chosen lag (None before the first command)."""
        return None if self._acting is None else self._acting[self.choice]

    def acting_all(self) -> np.ndarray | None:
        """N, the thrust acting now under each candidate lag (None before the first command)."""
        return None if self._acting is None else np.array(self._acting)

    def acting_scaled(self, factor: float, divisor: float) -> np.ndarray | None:
        """``acting_all() * factor / divisor`` (the acting thrusts' acceleration along a body axis over a mass),
        in one array; None before the first command."""
        return None if self._acting is None else np.array([a * factor / divisor for a in self._acting])

    def choose(self, index: int) -> None:
        """Take lag ``index``, told by a stronger excitation than hover gives (a mass step's fit); the running
        scores start over, so hover frames must build their own case before they switch back."""
        if index != self.choice:
            self.choice = int(index)
            self.switches += 1
            self._ms = [0.0] * len(self._ms)
            self._frames = 0
            self._imu_ms = [0.0] * len(self._imu_ms)
            self._imu_samples = 0

    def sent(self, thrust: float) -> None:
        """A command's thrust [N] was sent this tick."""
        thrust = float(thrust)
        if self._acting is None:
            self._acting = [thrust] * len(self._alpha)
        else:
            self._acting = [a + alpha * (thrust - a) for a, alpha in zip(self._acting, self._alpha)]

    def observe(self, v_z: float, bz_z: float, mass: float, gravity: float, other_z: float, fresh: bool,
                learn: bool = True) -> None:
        """One tick's vertical velocity; ``other_z`` is the rest of the predicted vertical acceleration (model
        residual and disturbance estimate), common to every candidate. ``learn`` False (a step being tracked,
        the thrust at its clamp): the frame is not scored, since the mass estimate itself is moving then."""
        if self._acting is None:
            return
        if self._v_prev is not None:
            dv, dt = v_z - self._v_prev, self._dt
            self._miss = [m + (dv - dt * (a * bz_z / mass - gravity + other_z))
                          for m, a in zip(self._miss, self._acting)]
        self._v_prev = v_z
        if not fresh:
            return
        if not learn:
            self._miss = [0.0] * len(self._miss)
            return
        self._frames += 1
        k = 1.0 / min(self._frames, MISS_FRAMES)
        self._ms = [(1.0 - k) * ms + k * m * m for ms, m in zip(self._ms, self._miss)]
        self._miss = [0.0] * len(self._miss)
        if self._frames >= MISS_FRAMES // 2 and self._imu_samples == 0:
            self._switch_to_best(self._ms)

    def observe_specific_force(self, f_z: float, theta: float, mass: float, learn: bool = True) -> None:
        """An accelerometer sample: the specific force along the body axis ``f_z`` [m/s^2] is the acting thrust
        times ``theta`` (nominal / true mass) over the nominal ``mass``. A direct reading of the thrust, where
        the frames give its second integral: on a quiet circle the frame-to-frame velocity misses were all noise
        and no lag won by the margin. Once samples come, they alone choose the lag."""
        if self._acting is None or not learn or not math.isfinite(f_z):
            return
        self._imu_samples += 1
        k = 1.0 / min(self._imu_samples, MISS_FRAMES)
        misses = [f_z - theta * a / mass for a in self._acting]
        self._imu_ms = [(1.0 - k) * ms + k * m * m for ms, m in zip(self._imu_ms, misses)]
        if self._imu_samples >= MISS_FRAMES // 2:
            self._switch_to_best(self._imu_ms)

    def _switch_to_best(self, ms: list[float]) -> None:
        best = first_argmin(ms)
        if best != self.choice and ms[best] < SWITCH_MARGIN * ms[self.choice]:
            self.choice = best
            self.switches += 1

    def forget_velocity(self) -> None:
        """Blind or off the air: the next velocity starts a new frame chain."""
        self._v_prev = None
        self._miss = [0.0] * len(self._miss)


def first_argmin(values: Sequence[float]) -> int:
    """``np.argmin`` on a short list of floats: the first NaN's index if there is one, else the first smallest's."""
    best = 0
    for i, x in enumerate(values):
        if x != x:  # NaN: numpy's argmin takes the first
            return i
        if x < values[best]:
            best = i
    return best


__all__ = ["ThrustLagBank", "first_argmin"]
