"""Where a fleet drone may land: a spot clear of every drone below it (docs/fleet.md).

A supervised landing descends straight down from where the drone is. In a stack, the drone
below sits on that line, so a drone told to land from there would land onto it. ``clear_spot``
finds the nearest point at the same height whose vertical line keeps ``clearance`` from every
given point (the drones below, and the spots they land on), inside the fence's soft box; the
drone moves there first, then lands. Pure functions.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

_DIRECTIONS = 24  # candidate directions around the drone (15 degrees apart)
_STEPS_PER_CLEARANCE = 10  # candidate distances: a tenth of the clearance apart
_MAX_CLEARANCES = 4  # look no further than four clearances away


def clear_spot(p: Sequence[float], others: Sequence[Sequence[float]], clearance: float,
               soft_lo: Sequence[float], soft_hi: Sequence[float],
               away_from: Sequence[float] | None = None) -> np.ndarray | None:
    """The point nearest ``p`` (same z) at least ``clearance`` from every point of ``others`` in x, y
    and inside the soft box in x, y; ``p`` itself when it is clear already; None when no point
    within four clearances is. Among equally near points, the one farthest from ``away_from``
    (x, y: the pattern's centre, so the drone leaves the others' path) wins."""
    here = np.asarray(p, dtype=float)[:3]
    pts = np.asarray(others, dtype=float).reshape(-1, 3)[:, :2]
    lo, hi = np.asarray(soft_lo, dtype=float)[:2], np.asarray(soft_hi, dtype=float)[:2]
    if pts.size == 0 or clearance <= 0:
        return here.copy()
    step = clearance / _STEPS_PER_CLEARANCE
    radii = step * np.arange(_STEPS_PER_CLEARANCE * _MAX_CLEARANCES + 1)
    angles = 2.0 * np.pi * np.arange(_DIRECTIONS) / _DIRECTIONS
    unit = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    for r in radii:
        cand = here[:2] + r * unit if r > 0 else here[None, :2]
        gap = np.linalg.norm(cand[:, None, :] - pts[None, :, :], axis=2).min(axis=1)
        inside = np.all((cand >= lo - 1e-12) & (cand <= hi + 1e-12), axis=1)
        ok = np.flatnonzero((gap >= clearance - 1e-9) & inside)
        if ok.size == 0:
            continue
        if away_from is not None and ok.size > 1:
            centre = np.asarray(away_from, dtype=float)[:2]
            ok = ok[np.argsort(-np.linalg.norm(cand[ok] - centre, axis=1), kind="stable")]
        return np.array([cand[ok[0], 0], cand[ok[0], 1], here[2]])
    return None


def below(p: Sequence[float], others: Sequence[Sequence[float] | None]) -> list[np.ndarray]:
    """The points of ``others`` lower than ``p`` (None entries skipped): what a descent from ``p`` passes."""
    z = float(p[2])
    return [np.asarray(q, dtype=float) for q in others if q is not None and float(q[2]) < z]


__all__ = ["below", "clear_spot"]
