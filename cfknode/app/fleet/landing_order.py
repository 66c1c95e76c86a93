"""Where a fleet drone lands and when it may descend: the geometry of an ordered landing.

``StackGeometry`` is the one rule both fleets apply (docs/fleet.md#separation): a drone lands at
least ``LANDING_CLEARANCE`` x ``fleet.min_separation`` (horizontally) from every drone below it,
from every spot another drone lands on below it and from the spots of the drones above it (which
descend through there), and it does not descend while a flying drone is below it within the
separation. The one-process fleet's ``FleetCoordinator`` asks it with the positions it sees at
every tick; a Ray actor asks it through ``ViewGate`` with the fleet as the driver last told it
(docs/fleet-ray.md), so a Ray fleet lands a stack bottom-up too.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from cfknode.safety.geofence import Geofence
from cfknode.safety.landing_spot import below, clear_spot

FLYING = ("TAKEOFF", "TRACK", "LAND")
# A drone lands at least this many min_separations (horizontally) from every drone below it, gliding
# there first at GLIDE_SPEED: a drone's downwash reaches further down than sideways.
LANDING_CLEARANCE = 1.5
GLIDE_SPEED = 0.4  # m/s


@dataclass(frozen=True)
class StackGeometry:
    min_separation: float
    soft_lo: np.ndarray
    soft_hi: np.ndarray
    centre: tuple[float, float]  # the pattern's centre: a drone glides away from it

    @classmethod
    def from_config(cls, cfg: Any) -> "StackGeometry":
        fence = Geofence.from_config(cfg.safety)
        return cls(float(cfg.fleet.min_separation), fence.soft_lo, fence.soft_hi,
                   (float(cfg.trajectory.center[0]), float(cfg.trajectory.center[1])))

    def spot(self, k: int, p: Sequence[float], positions: Sequence[Any], spots: Mapping[int, Any]
             ) -> tuple[np.ndarray, float]:
        """Where drone k at ``p`` lands (same height) and how long it glides there: clear of every
        drone below it and of their spots, and of the spots of the drones above it."""
        z = float(p[2])
        others_spots = [np.asarray(q, dtype=float) for j, q in spots.items() if j != k and q is not None]
        others = [*below(p, [*(q for j, q in enumerate(positions) if j != k), *others_spots]),
                  *(q for q in others_spots if float(q[2]) > z)]
        spot = clear_spot(p, others, LANDING_CLEARANCE * self.min_separation, self.soft_lo, self.soft_hi,
                          away_from=self.centre)
        if spot is None:
            return np.asarray(p, dtype=float).copy(), 0.0  # nowhere clear: land in place (and logged as close)
        distance = float(np.hypot(*(spot[:2] - np.asarray(p, dtype=float)[:2])))
        return spot, (distance / GLIDE_SPEED if distance > 0 else 0.0)

    def blocked(self, k: int, p: Sequence[float] | None, positions: Sequence[Any], states: Sequence[str]) -> bool:
        """Whether a flying drone is below drone k (at ``p``) within the separation, horizontally."""
        if p is None:
            return False
        for j, q in enumerate(positions):
            if j != k and q is not None and states[j] in FLYING and float(q[2]) < float(p[2]):
                if float(np.hypot(q[0] - p[0], q[1] - p[1])) < self.min_separation:
                    return True
        return False


    def over(self, k: int, positions: Sequence[Any]) -> bool:
        """Whether any drone (flying or not) is below drone k within the separation, horizontally."""
        p = positions[k]
        if p is None or self.min_separation <= 0:
            return False
        for j, q in enumerate(positions):
            if j != k and q is not None and float(q[2]) < float(p[2]):
                if float(np.hypot(q[0] - p[0], q[1] - p[1])) < self.min_separation:
                    return True
        return False


class StallHold:
    """What drone k's radio holds if the fleet's loop stalls (backends/stale_setpoint.py): level at
    its hover thrust while a drone is below it, else the descending hold; told on change only."""

    def __init__(self, radio: Any, hover_thrust: int) -> None:
        self._radio, self._thrust, self.level = radio, int(hover_thrust), False

    def set(self, level: bool) -> None:
        if level != self.level:
            self.level = level
            self._radio.hold_level(self._thrust if level else None)


class ViewGate:
    """Drone k's ``LandingGate`` (safety/ordered_landing.py) where the fleet is elsewhere (a Ray actor):
    ``update`` (any thread) hands it every drone's latest position, supervisor state and landing spot
    as the driver knows them; ``spot`` and ``blocked`` (the flight's thread) judge by that and the
    drone's own position. ``spot_now`` is the spot it chose last, which the driver passes on."""

    def __init__(self, geometry: StackGeometry, k: int, note: Callable[[str], None] | None = None) -> None:
        self._geo, self._k, self._note = geometry, k, note
        self._lock = threading.Lock()
        self._positions: list[Any] = []
        self._states: list[str] = []
        self._spots: dict[int, Any] = {}
        self.spot_now: tuple[float, float, float] | None = None
        self._waiting = False

    def update(self, positions: Sequence[Any], states: Sequence[str], spots: Mapping[int, Any]) -> None:
        with self._lock:
            self._positions = [None if q is None else np.asarray(q, dtype=float) for q in positions]
            self._states, self._spots = list(states), dict(spots)

    def _view(self, p: Sequence[float]) -> tuple[list[Any], list[str], dict[int, Any]]:
        with self._lock:
            positions, states, spots = list(self._positions), list(self._states), dict(self._spots)
        while len(positions) <= self._k:
            positions.append(None)
            states.append("")
        positions[self._k] = np.asarray(p, dtype=float)
        return positions, states, spots

    def spot(self, p: np.ndarray) -> tuple[np.ndarray, float]:
        positions, _, spots = self._view(p)
        spot, move_s = self._geo.spot(self._k, p, positions, spots)
        self.spot_now = tuple(float(v) for v in spot)
        return spot, move_s

    def blocked(self, p: np.ndarray) -> bool:
        positions, states, _ = self._view(p)
        if not self._geo.blocked(self._k, p, positions, states):
            self._waiting = False
            return False
        if not self._waiting and self._note is not None:
            self._note("waits to land: a flying drone is below it")
        self._waiting = True
        return True


__all__ = ["FLYING", "GLIDE_SPEED", "LANDING_CLEARANCE", "StackGeometry", "StallHold", "ViewGate"]
