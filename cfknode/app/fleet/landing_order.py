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
import time
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
# A Ray actor descends only on a view of the fleet at most this far behind its own flight time: a drone
# below moves at most GLIDE_SPEED x this (0.1 m) inside the spot's 0.15 m of clearance over the separation.
VIEW_LAG_S = 0.25
# Wall seconds a lockstep actor waits for a view that does not move (a drone that started late, or hung until
# the driver has its ending) before it hovers on in flight time instead: a silent drone never holds it for long.
SILENT_S = 5.0


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
    ``update`` (any thread) hands it every drone's latest position, supervisor state, landing spot and
    flight time as the driver knows them; ``spot`` and ``blocked`` (the flight's thread) judge by that
    and the drone's own position. ``spot_now`` is the spot it chose last, which the driver passes on.

    Once the actor tells it its own flight time (``at``), it never lets the drone begin a descent on a
    view older than ``VIEW_LAG_S`` of that time, or on no view at all: each actor's lockstep clock runs
    at its own pace, so the driver's newest word on a drone below may be seconds of its flight behind,
    from before it took off. Then a lockstep actor calls ``catch_up`` after its tick, which holds the
    loop (and so its simulator) until the view has caught up. On the way down only a flying drone below
    stops it, as in the one-process fleet, not a late view."""

    def __init__(self, geometry: StackGeometry, k: int, note: Callable[[str], None] | None = None,
                 wall: Callable[[], float] = time.monotonic) -> None:
        self._geo, self._k, self._note, self._wall = geometry, k, note, wall
        self._cond = threading.Condition()
        self._positions: list[Any] = []
        self._states: list[str] = []
        self._spots: dict[int, Any] = {}
        self._times: list[float] | None = None  # every drone's flight time, as told; None: nothing told yet
        self._moved = wall()  # when the slowest other drone's told time last moved (wall)
        self._now: float | None = None  # this drone's own flight time
        self.spot_now: tuple[float, float, float] | None = None
        self._waiting = ""  # why it waits to descend ("view", "below" or "")
        self.caught_up_s = 0.0  # wall seconds its loop has waited for the view, in all

    def update(self, positions: Sequence[Any], states: Sequence[str], spots: Mapping[int, Any],
               times: Sequence[float] = ()) -> None:
        """The fleet as the driver knows it; ``times``: each drone's latest flight time (inf once its
        flight has ended, 0 before its first tick)."""
        with self._cond:
            before = self._slowest()
            self._positions = [None if q is None else np.asarray(q, dtype=float) for q in positions]
            self._states, self._spots = list(states), dict(spots)
            self._times = [float(t) for t in times]
            if before is None or self._slowest() > before:
                self._moved = self._wall()
            self._cond.notify_all()

    def at(self, t: float) -> None:
        """This drone's flight time (its latest tick)."""
        self._now = float(t)

    def _slowest(self) -> float | None:
        """The slowest other drone's told time (under ``_cond``); None before the first view."""
        if self._times is None:
            return None
        return min((t for j, t in enumerate(self._times) if j != self._k), default=float("inf"))

    def _view(self, p: Sequence[float]) -> tuple[list[Any], list[str], dict[int, Any]]:
        with self._cond:
            positions, states, spots = list(self._positions), list(self._states), dict(self._spots)
        while len(positions) <= self._k:
            positions.append(None)
            states.append("")
        positions[self._k] = np.asarray(p, dtype=float)
        return positions, states, spots

    def _late(self) -> float | None:
        """How far the view is behind this drone's own flight time (under ``_cond``); None with no view yet."""
        slowest = self._slowest()
        return None if slowest is None or self._now is None else self._now - slowest

    def behind(self) -> str:
        """Why the view is too old to begin a descent on ("" when it is not)."""
        if self._now is None:
            return ""  # not told its own time: judged by the view as it is
        with self._cond:
            late = self._late()
        if late is None:
            return "no view of the fleet yet"
        return f"the fleet's view is {late:.2f} s behind its own flight time" if late > VIEW_LAG_S else ""

    def catch_up(self) -> None:
        """After a tick, on the loop's thread (lockstep only): while the drone waits to descend on a late
        view, hold the loop until the view catches up, or has not moved for ``SILENT_S`` (then it hovers
        on in flight time, asking again each tick)."""
        if self._waiting != "view" or self._now is None:
            return
        start = self._wall()
        with self._cond:
            while True:
                late, left = self._late(), self._moved + SILENT_S - self._wall()
                if (late is not None and late <= VIEW_LAG_S) or left <= 0.0:
                    break
                self._cond.wait(timeout=left)
        self.caught_up_s += self._wall() - start

    def spot(self, p: np.ndarray) -> tuple[np.ndarray, float]:
        positions, _, spots = self._view(p)
        spot, move_s = self._geo.spot(self._k, p, positions, spots)
        self.spot_now = tuple(float(v) for v in spot)
        return spot, move_s

    def blocked(self, p: np.ndarray, descending: bool = False) -> bool:
        positions, states, _ = self._view(p)
        why = "" if descending else self.behind()
        kind = "view" if why else ""
        if not why and self._geo.blocked(self._k, p, positions, states):
            why, kind = "a flying drone is below it", "below"
        if kind and kind != self._waiting and self._note is not None:
            self._note(f"waits to land: {why}")  # once per wait, not every tick
        self._waiting = kind
        return bool(kind)


__all__ = ["FLYING", "GLIDE_SPEED", "LANDING_CLEARANCE", "SILENT_S", "StackGeometry", "StallHold", "VIEW_LAG_S",
           "ViewGate"]
