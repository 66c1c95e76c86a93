"""Minimum separation between the drones of a fleet: predicted before take-off, watched in flight.

Before take-off, every pair's references are sampled on a fine grid over the whole flight
(ground start and landing spot included: they are places too); the first time a pair comes
closer than the minimum refuses the flight, naming the pair, the time and the distance.
In flight, ``SeparationWatch`` compares the drones' latest positions (their state estimates,
as on hardware) and reports a pair when it comes too close, and again only after it has
parted (held and landing drones are watched too); what to do about it (hold, then land) is
the fleet's business (cfknode/app/fleet/coordinator.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from cfknode.kernel.reference import Reference

GRID_S = 0.01  # s between checked reference samples (0.4 m/s moves 4 mm)
REARM_M = 0.05  # m beyond the minimum a reported pair must part before a new approach is reported


@dataclass(frozen=True)
class Closest:
    """The closest approach of one pair: drones ``a`` and ``b`` (names), at ``t``, ``distance`` apart."""

    a: str
    b: str
    t: float
    distance: float


def closest_approach(names: Sequence[str], refs: Sequence[Reference], grid_s: float = GRID_S) -> Closest | None:
    """The closest pair of references over the longest of their flights (None for fewer than two)."""
    if len(refs) < 2:
        return None
    t_end = max(r.duration for r in refs)
    t = np.arange(0.0, t_end + grid_s, grid_s)
    ps = [r.sample(t).p for r in refs]
    best: Closest | None = None
    for i in range(len(refs)):
        for j in range(i + 1, len(refs)):
            d = np.linalg.norm(ps[i] - ps[j], axis=1)
            k = int(np.argmin(d))
            if best is None or d[k] < best.distance:
                best = Closest(names[i], names[j], float(t[k]), float(d[k]))
    return best


def first_violation(names: Sequence[str], refs: Sequence[Reference], min_separation: float,
                    grid_s: float = GRID_S) -> Closest | None:
    """The earliest time any pair's references come closer than ``min_separation`` (None: never)."""
    if len(refs) < 2 or min_separation <= 0:
        return None
    t_end = max(r.duration for r in refs)
    t = np.arange(0.0, t_end + grid_s, grid_s)
    ps = [r.sample(t).p for r in refs]
    first: Closest | None = None
    for i in range(len(refs)):
        for j in range(i + 1, len(refs)):
            d = np.linalg.norm(ps[i] - ps[j], axis=1)
            close = np.flatnonzero(d < min_separation)
            if close.size and (first is None or t[close[0]] < first.t):
                k = int(close[0])
                first = Closest(names[i], names[j], float(t[k]), float(d[k]))
    return first


def refusal(names: Sequence[str], refs: Sequence[Reference], min_separation: float) -> str | None:
    """One line refusing the flight when the references come too close, else None."""
    v = first_violation(names, refs, min_separation)
    if v is None:
        return None
    return (f"take-off refused: the references of {v.a} and {v.b} come {v.distance:.3f} m apart at t = {v.t:.2f} s, "
            f"closer than fleet.min_separation {min_separation:g} m")


class SeparationWatch:
    """Latest positions of the fleet; ``update`` returns the pairs that just came too close."""

    def __init__(self, names: Sequence[str], min_separation: float) -> None:
        self.names = tuple(names)
        self.min_separation = float(min_separation)
        self._p: list[tuple[float, float, float] | None] = [None] * len(names)
        self._reported: set[tuple[int, int]] = set()
        self.closest = math.inf  # the smallest distance seen between any two drones, m

    def update(self, i: int, p: Sequence[float], active: Sequence[bool]) -> list[tuple[int, int, float]]:
        """Drone ``i`` is at ``p``; ``active[k]``: drone k is flying (a pair of landed drones is no risk)."""
        x, y, z = (float(v) for v in p)
        self._p[i] = (x, y, z)
        out = []
        for j, q in enumerate(self._p):
            if j == i or q is None or not (active[i] or active[j]):
                continue
            d = math.sqrt((x - q[0]) ** 2 + (y - q[1]) ** 2 + (z - q[2]) ** 2)
            if d < self.closest:
                self.closest = d
            pair = (min(i, j), max(i, j))
            if pair in self._reported and d > self.min_separation + REARM_M:
                self._reported.discard(pair)  # apart again: a new approach (in a hold, a landing) is reported too
            if self.min_separation > 0 and d < self.min_separation and pair not in self._reported:
                self._reported.add(pair)
                out.append((pair[0], pair[1], d))
        return out


__all__ = ["Closest", "SeparationWatch", "closest_approach", "first_violation", "refusal"]
