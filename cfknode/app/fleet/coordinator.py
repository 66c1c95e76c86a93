"""The fleet's coordinator: separation watch, fault policy and ordered landings (docs/fleet.md).

``FleetCoordinator`` is a tick observer of every drone (``tap(i)``). Two drones closer than
``fleet.min_separation``: both hover for ``fleet.hold_s``, then land. One drone's supervisor
lands or stops it: ``fleet.on_fault`` says what the others do. A drone the fleet lands first
glides clear of every drone below it (``safety/landing_spot.py``), and does not descend while
a flying drone is below it: a stack lands from the bottom up, never one drone onto another.
Every supervised landing of a drone (a stop signal, ``cfknode estop --land``, a fault of its own)
is ordered the same way: ``landing_planner(i)`` is the planner its supervisor flies it with
(safety/ordered_landing.py), this coordinator its gate.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from cfknode.app.config import Config
from cfknode.app.fleet.landing_order import FLYING as _FLYING
from cfknode.app.fleet.landing_order import GLIDE_SPEED, LANDING_CLEARANCE, StackGeometry
from cfknode.flight.controller import TickInfo
from cfknode.flight.formation import HoldableReference
from cfknode.safety.ordered_landing import OrderedLanding
from cfknode.safety.part_errors import signal_stop_text
from cfknode.safety.separation import SeparationWatch
from cfknode.safety.supervisor import Supervisor
_FAILED = ("LAND", "EMERGENCY", "IDLE", "LANDED")
# The fleet's own landings never trigger the fault policy; nor do stop signals, which every drone got.
_OWN_CAUSES = ("separation", "fleet_fault", "sigint", "sigterm", "sighup")


class FleetCoordinator:
    """Separation watch and fault policy across the fleet; a tick observer of every drone (``tap(i)``)."""

    def __init__(self, cfg: Config, names: Sequence[str], supervisors: Sequence[Supervisor],
                 refs: Sequence[HoldableReference], log: Any, stall_holds: Sequence[Any] = ()) -> None:
        """``stall_holds``: each drone's ``landing_order.StallHold`` (wall-clock fleets), told at every
        tick whether a drone is below it, so a stall's hold is level there (docs/fleet.md)."""
        self.names = list(names)
        self._sups = list(supervisors)
        self._refs = list(refs)
        self._log = log
        self._policy = cfg.fleet.on_fault
        self._hold_s = cfg.fleet.hold_s
        self._period = 1.0 / cfg.controller.rate_hz
        # The nominal landing starts here; a held drone must be landing before it (the
        # supervisor's nominal landing would otherwise follow the held reference and cut in the air).
        self._land_deadline = [r.segments["land"][0] - 2.0 * self._period for r in refs]
        self.watch = SeparationWatch(names, cfg.fleet.min_separation)
        self.geometry = StackGeometry.from_config(cfg)  # where a drone lands, when it may descend
        self._stall_holds = list(stall_holds)
        self._spots: dict[int, np.ndarray] = {}  # where each drone glides before it lands (clear of those below)
        self._glide_end: dict[int, float] = {}  # flight time each drone's glide there ends
        self._state = [""] * len(names)
        self._p: list[np.ndarray | None] = [None] * len(names)
        self._land_at: dict[int, tuple[float, str, str]] = {}
        self._faulted: set[int] = set()
        self._signals: deque[str] = deque()  # stop signals not yet on /events (a handler must not write the log)
        self._signals_logged = 0
        self._waiting: set[int] = set()  # drones whose ordered landing waits for one below (logged once)
        self._now = 0.0
        self.events: list[str] = []

    def tap(self, i: int) -> "_Tap":
        return _Tap(self, i)

    def landing_planner(self, k: int) -> Callable[[np.ndarray, float, float, float], OrderedLanding]:
        """Drone k's supervised landings: glide clear of the drones below, wait for them, then descend."""
        gate = _Gate(self, k)
        return lambda start, ground_z, t0, speed: OrderedLanding(gate, start, ground_z, t0, speed)

    def interrupt(self, signal_name: str = "SIGINT") -> None:
        """A stop signal for the whole fleet: every drone's supervisor gets it (the first lands,
        a second stops the motors). Safe in a signal handler: it only appends to queues."""
        self._signals.append(signal_name)
        for sup in self._sups:
            sup.interrupt(signal_name)

    def log_signals(self, t: float) -> None:
        """Put the stop signals received since the last call on ``/events`` at time ``t``."""
        while self._signals:
            name = self._signals.popleft()
            self._signals_logged += 1
            text = signal_stop_text(name)
            if self._signals_logged == 1:
                again = "Ctrl-C again" if name == "SIGINT" else f"another {name} (or Ctrl-C)"
                self._event(t, "warning", f"{text}: every drone lands; {again} stops them all")
            else:
                self._event(t, "error", f"{text} again: every drone stops its motors")

    def on_tick(self, i: int, info: TickInfo) -> None:
        t = self._now = info.t
        if self._signals:
            self.log_signals(t)
        if info.est is not None:
            self._p[i] = info.est.p
        if self._stall_holds:
            self._stall_holds[i].set(self.geometry.over(i, self._p))
        pending = self._land_at.get(i)
        # Bottom up: not while a flying drone is below (until its nominal landing would start).
        if pending is not None and t >= pending[0] - 1e-9 and (t >= self._land_deadline[i] or not self._blocked(i)):
            del self._land_at[i]
            self._sups[i].request_land(pending[1], pending[2])
        state = info.supervisor_state
        if state != self._state[i]:
            self._state[i] = state
            if state in _FAILED and i not in self._faulted:
                cause = self._sups[i].snapshot().cause
                if cause and not cause.startswith(_OWN_CAUSES):
                    self._faulted.add(i)
                    self._on_fault(i, t, cause)
        if info.est is not None:
            active = [s in _FLYING for s in self._state]
            for a, b, d in self.watch.update(i, info.est.p, active):
                self._event(t, "error", f"{self.names[a]} and {self.names[b]} are {d:.3f} m apart, under "
                            f"fleet.min_separation {self.watch.min_separation:g} m: both hold, then land")
                for k in self._bottom_up((a, b)):
                    self._hold_then_land(k, t, t + self._hold_s, f"too close to {self.names[b if k == a else a]} "
                                         f"({d:.3f} m)", "separation")

    def _on_fault(self, i: int, t: float, cause: str) -> None:
        others = [k for k in range(len(self.names)) if k != i]
        self._event(t, "warning", f"{self.names[i]} ended its flight ({cause}); fleet.on_fault {self._policy}")
        if self._policy == "land_all":
            for k in self._bottom_up(others):  # at once, or as soon as it has glided clear of those below
                self._hold_then_land(k, t, t, f"fleet: {self.names[i]} failed ({cause})", "fleet_fault")
        elif self._policy == "hold":
            for k in self._bottom_up(others):
                self._hold_then_land(k, t, self._land_deadline[k], f"fleet: {self.names[i]} failed ({cause}); "
                                     "held, then landed", "fleet_fault")

    def _hold_then_land(self, k: int, t: float, t_land: float, reason: str, cause: str) -> None:
        """Hold drone k (gliding clear of the drones below it first), then land it at ``t_land`` or
        once the glide ends, whichever is later, never after its nominal landing starts."""
        if self._state[k] not in ("TAKEOFF", "TRACK"):
            if self._state[k] in ("", "IDLE", "PREFLIGHT"):
                self._sups[k].request_land(reason, cause)  # refuses a take-off not yet made
            return  # already landing, landed or stopped: nothing to hold
        p = self._p[k]
        if p is not None and k not in self._spots:  # held already: its first spot and glide stand
            spot, move_s = self._landing_spot(k, p)
            self._spots[k], self._glide_end[k] = spot, t + move_s
            if move_s > 0.0:
                self._refs[k].hold(t, p, to=spot, move_s=move_s)
            elif t_land > t:
                self._refs[k].hold(t, p)
        t_land = max(t_land, self._glide_end.get(k, t_land))  # not before it is clear of those below
        if t_land <= t and not self._blocked(k):
            self._sups[k].request_land(reason, cause)  # clear of those below: it lands where it is, now
            return
        self._schedule_land(k, min(t_land, self._land_deadline[k]), reason, cause)

    def _landing_spot(self, k: int, p: np.ndarray) -> tuple[np.ndarray, float]:
        """Where drone k lands (clear of every drone below it and of their spots, and of the spots of
        the drones above it, which descend through there) and the glide's duration."""
        return self.geometry.spot(k, p, self._p, self._spots)

    def _bottom_up(self, drones: Sequence[int]) -> list[int]:
        """``drones``, lowest first: each one's spot then avoids the spots of those below it."""
        return sorted(drones, key=lambda k: float(self._p[k][2]) if self._p[k] is not None else 0.0)

    def _blocked(self, k: int) -> bool:
        """Whether a flying drone is below drone k within the separation, horizontally: k waits to land."""
        return self.geometry.blocked(k, self._p[k], self._p, self._state)

    def _schedule_land(self, k: int, t_land: float, reason: str, cause: str) -> None:
        """Land drone k at its time ``t_land`` (the earliest schedule wins); on_tick requests it."""
        if k not in self._land_at or t_land < self._land_at[k][0]:
            self._land_at[k] = (t_land, reason, cause)

    def _event(self, t: float, level: str, text: str) -> None:
        self.events.append(f"{t:.3f} s {level}: {text}")
        self._log.write("/events", t, {"level": level, "text": text, "source": "fleet"})


@dataclass
class _Gate:
    """Drone k's ``LandingGate`` (safety/ordered_landing.py): the coordinator's spots and bottom-up order."""

    coordinator: FleetCoordinator
    k: int

    def spot(self, p: np.ndarray) -> tuple[np.ndarray, float]:
        co, k = self.coordinator, self.k
        spot, move_s = co._landing_spot(k, p)
        co._spots[k] = spot
        return spot, move_s

    def blocked(self, p: np.ndarray, descending: bool = False) -> bool:
        co, k = self.coordinator, self.k
        if not co._blocked(k):
            co._waiting.discard(k)
            return False
        if k not in co._waiting:
            co._waiting.add(k)
            co._event(co._now, "info", f"{co.names[k]} waits to land: a flying drone is below it")
        return True


@dataclass
class _Tap:
    coordinator: FleetCoordinator
    index: int

    def on_tick(self, tick: TickInfo) -> None:
        self.coordinator.on_tick(self.index, tick)


__all__ = ["FleetCoordinator", "GLIDE_SPEED", "LANDING_CLEARANCE"]
