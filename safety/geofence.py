"""The geofence: a world-frame box with a soft margin inside it and a stop distance outside.

Three nested regions (the firmware has no geofence, so the host keeps one on the mocap pose:
docs/hardware.md#host-safety):

- the *soft box* (the box shrunk by ``margin``, except at the floor): every reference is
  clamped into it, so the controller never aims at the fence itself;
- the *hard box*: a position outside it lands the drone;
- the box grown by ``stop_distance``: a position beyond it stops the motors (a runaway).

The floor is not shrunk: landing references end on the ground, and the ground cannot be
flown through anyway. All functions are pure; the per-tick ones work on plain floats.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cfknode.kernel.errors import ConfigError
from cfknode.safety.settings import SafetyConfig
from cfknode.kernel.reference import RefSamples

_AXES = "xyz"


@dataclass(frozen=True)
class Geofence:
    lo: tuple[float, float, float]  # hard box, m
    hi: tuple[float, float, float]
    margin: float  # m, soft box inset (sides and ceiling)
    stop_distance: float  # m outside the hard box

    @classmethod
    def from_config(cls, cfg: SafetyConfig) -> Geofence:
        lo, hi = tuple(cfg.fence_min), tuple(cfg.fence_max)
        for i, axis in enumerate(_AXES):
            # The soft box must keep some room on every side (2 cm), or nothing could be flown.
            span = hi[i] - lo[i] - (2.0 if i < 2 else 1.0) * cfg.fence_margin
            if span <= 0.02:
                raise ConfigError(
                    f"config keys 'safety.fence_min/fence_max' leave no room on {axis} inside the "
                    f"{cfg.fence_margin} m margin: {lo[i]} .. {hi[i]}"
                )
        return cls(lo, hi, cfg.fence_margin, cfg.fence_stop_distance)

    @property
    def soft_lo(self) -> np.ndarray:
        return np.array([self.lo[0] + self.margin, self.lo[1] + self.margin, self.lo[2]])

    @property
    def soft_hi(self) -> np.ndarray:
        return np.array(self.hi) - self.margin

    def margin_of(self, x: float, y: float, z: float) -> tuple[float, int]:
        """Signed distance inside the hard box (< 0: outside by that much) and the axis that sets it."""
        lo, hi = self.lo, self.hi
        best, axis = math.inf, 0
        for i, v in enumerate((x, y, z)):
            d = min(v - lo[i], hi[i] - v)
            if d < best:
                best, axis = d, i
        return best, axis

    def excursion(self, p: np.ndarray) -> np.ndarray:
        """How far each position (n, 3) is outside the hard box, m (0 inside); NaN rows give 0."""
        p = np.atleast_2d(np.asarray(p, dtype=float))
        out = np.maximum(np.asarray(self.lo) - p, p - np.asarray(self.hi))
        dist = np.linalg.norm(np.maximum(out, 0.0), axis=1)
        return np.nan_to_num(dist, nan=0.0)

    def contains_soft(self, p: np.ndarray) -> bool:
        """Whether every position (n, 3) is inside the soft box."""
        p = np.atleast_2d(p)
        return bool(np.all(p >= self.soft_lo - 1e-12) and np.all(p <= self.soft_hi + 1e-12))

    def clamp_point(self, p: np.ndarray) -> np.ndarray:
        """A position moved into the soft box (a new array)."""
        return np.minimum(np.maximum(p, self.soft_lo), self.soft_hi)


def clamp_reference(ref: RefSamples, soft_lo: np.ndarray, soft_hi: np.ndarray) -> RefSamples:
    """``ref`` with every node clamped into the soft box; a clamped coordinate holds still there
    (its velocity and acceleration are zeroed), so the reference stays consistent. Returns ``ref``
    itself when nothing needed clamping (the common case costs two comparisons of the arrays)."""
    p = ref.p
    below = p < soft_lo
    above = p > soft_hi
    if not (below.any() or above.any()):
        return ref
    outside = below | above
    v = np.where(outside, 0.0, ref.v)
    a = np.where(outside, 0.0, ref.a)
    return RefSamples(t=ref.t, p=np.minimum(np.maximum(p, soft_lo), soft_hi), v=v, a=a, yaw=ref.yaw)


def axis_name(i: int) -> str:
    return _AXES[i]
