"""What the fast layer tells the controller each tick, and what it flies with where an axis does not act.

Besides the three estimates it carries the layer's state (frozen, saturated, tracking a step, the axes that
act), so ``Command``, ``TickInfo``, the log and the summary show when the layer is not learning.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np


@dataclass(frozen=True, slots=True)
class AdaptationEstimate:
    offset: np.ndarray  # (3,) m/s^2, added to the model's acceleration
    thrust_scale: float  # estimated mass / nominal mass
    axis_gain: np.ndarray  # (3,) delivered / commanded horizontal acceleration (z is 1)
    frozen: bool = False  # no update this tick (stale pose or not flying)
    saturated: bool = False  # the last applied command was at the thrust clamp or the tilt limit
    stepping: bool = False  # a vertical step was detected and is being tracked at the step bandwidth
    acts: tuple[bool, bool, bool] = (True, True, True)  # x, y, vertical: the estimate acts there (see engagement)

    @classmethod
    def neutral(cls) -> AdaptationEstimate:
        return cls(np.zeros(3), 1.0, np.ones(3))

    def to_log(self) -> dict[str, object]:
        # Lists, not arrays: the log's encoder converts arrays in a slow fallback, 400 times a second.
        return {"offset": self.offset.tolist(), "thrust_scale": self.thrust_scale,
                "axis_gain": self.axis_gain[:2].tolist(),
                "frozen": self.frozen, "saturated": self.saturated, "stepping": self.stepping, "acts": list(self.acts)}


def applied_estimate(estimate: AdaptationEstimate, acts: Sequence[bool] | np.ndarray) -> AdaptationEstimate:
    """What the controller flies with: ``estimate`` on the axes that act, the model alone on the others
    (offset 0; thrust scale 1 and axis gain 1 where the vertical / that horizontal axis does not act)."""
    ax, ay, az = bool(acts[0]), bool(acts[1]), bool(acts[2])
    if ax and ay and az:
        return estimate
    if not (ax or ay or az):  # a quiet flight's every tick: the model alone
        offset, gain = _ZERO.copy(), _ONES.copy()
    else:
        o, k = estimate.offset, estimate.axis_gain
        offset = np.array([o[0] if ax else 0.0, o[1] if ay else 0.0, o[2] if az else 0.0])
        gain = np.array([k[0] if ax else 1.0, k[1] if ay else 1.0, k[2]])
    return AdaptationEstimate(offset, estimate.thrust_scale if az else 1.0, gain, estimate.frozen, estimate.saturated,
                              estimate.stepping, (ax, ay, az))


_ZERO = np.zeros(3)
_ONES = np.ones(3)


__all__ = ["AdaptationEstimate", "applied_estimate"]
