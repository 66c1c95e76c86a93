"""What the radio sends when the flight loop's newest setpoint is old: the loop has stalled.

The loop stamps each setpoint when it hands it to the radio (``StaleGuard.stamp``); the radio's
TX thread asks ``StaleGuard.outgoing`` what to send at every slot. By the setpoint's age:

- fresh: the setpoint as the loop sent it;
- resent for ``hold_slots`` TX slots: a level, descending hold: roll = pitch = yaw
  rate = 0 and the supervisor's blind thrust (a little under hover), never more than the loop
  last asked for;
- then older than ``stop_after_s`` (under the firmware's 2 s commander-watchdog lock,
  docs/hardware.md#commander-watchdog): zeros, motors off, and no more e-stop heartbeats. This
  is latched: a loop that comes back later does not restart the motors.

In a fleet, a drone with another one below it (``hold_level``, kept up to date by the fleet's
coordinator at every tick) holds level instead: the hover thrust, never more than the loop last
asked for, so a stalled stack does not sink onto the drone below; the lowest drone descends.

A setpoint with zero thrust is never replaced: the motors are already off, and a landed drone
whose loop has ended (the fleet's others still flying) must keep its heartbeat. An operator's
stop (``operator_stop``: ``cfknode estop``) stops the motors as soon as the loop is stalled,
at once or at the hold it would otherwise fly. The listener
(the supervisor) hears of each hold and stop with the setpoint's age, and of a loop that came
back during a hold with how long it was gone, from the thread that noticed it.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Callable

Setpoint = tuple[float, float, float, int]  # roll deg, pitch deg, yaw rate deg/s, thrust command
ZERO: Setpoint = (0.0, 0.0, 0.0, 0)

FRESH, HOLD, STOP = "fresh", "hold", "stop"
RESUMED = "resumed"  # told, never a phase: the loop came back during a hold, with the stall's length
STOP_SIGNALS_DURING_STALL = 2  # as in flight: the first stop signal lands (the hold), the second stops


@dataclass(frozen=True)
class StalePolicy:
    """When a setpoint counts as stale: held once ``hold_slots`` TX slots went by without a new
    one, motors off once it is also older than ``stop_after_s``.

    Slots the TX thread itself saw, not age alone: a whole process descheduled for a moment
    (a loaded host) wakes with an old stamp, but its loop stamps again before that many slots."""

    hold_slots: int
    stop_after_s: float

    def __post_init__(self) -> None:
        if not (isinstance(self.hold_slots, int) and self.hold_slots >= 1):
            raise ValueError(f"hold_slots must be an integer >= 1, got {self.hold_slots!r}")
        if not (0.0 < self.stop_after_s and math.isfinite(self.stop_after_s)):
            raise ValueError(f"stop_after_s must be a positive number of seconds, got {self.stop_after_s!r}")


def stale_phase(age: float, slots: int, policy: StalePolicy) -> str:
    """FRESH, HOLD or STOP for a setpoint ``age`` seconds old that ``slots`` TX slots have resent
    (a NaN age past the hold counts as stopped)."""
    if slots < policy.hold_slots:
        return FRESH
    if age <= policy.stop_after_s:
        return HOLD
    return STOP


def hold_setpoint(last: Setpoint, hold_thrust: int) -> Setpoint:
    """Level, no yaw rate, the hold thrust but never more than ``last`` asked for (so it sinks)."""
    return (0.0, 0.0, 0.0, min(int(last[3]), int(hold_thrust)))


class StaleGuard:
    """The setpoint slot with its stamp, and the phase it is in (see the module docstring).

    ``stamp`` runs on the loop's thread, ``outgoing`` on the radio's, ``stop_signal`` on the
    signal relay's: each replaces or reads whole values, and the phase changes under a lock.
    """

    def __init__(self, policy: StalePolicy, clock: Callable[[], float], hold_thrust: int = 0) -> None:
        self.policy = policy
        self._clock = clock
        self._hold_thrust = int(hold_thrust)
        self._slot: tuple[Setpoint, float] | None = None
        self._seen: tuple[Setpoint, float] | None = None  # the slot at the previous ``outgoing``
        self._slots = 0  # TX slots that resent the same stamped setpoint
        self._phase = FRESH
        self._lock = threading.Lock()
        self._listener: Callable[[str, float], None] | None = None
        self._operator_stop = False  # an operator asked for the motors off: no hold, a stop
        self._level_thrust: int | None = None  # a drone below: the hold is level, at this (hover) thrust
        self.holds = 0  # stalls that reached the hold
        self.stops = 0  # stalls that reached the stop (at most one: it latches)

    def set_hold(self, hold_thrust: int, listener: Callable[[str, float], None] | None) -> None:
        """The hold's thrust (the supervisor's blind thrust) and who hears of a phase change."""
        self._hold_thrust = int(hold_thrust)
        self._listener = listener

    def hold_level(self, thrust: int | None) -> None:
        """A drone is below this one (any thread): a hold keeps ``thrust`` (its hover thrust, never more
        than the loop last asked for) instead of the descending hold thrust; None: descend again."""
        self._level_thrust = None if thrust is None else int(thrust)

    @property
    def phase(self) -> str:
        return self._phase

    @property
    def stopped(self) -> bool:
        """Motors off for good: the e-stop heartbeat must stop too."""
        return self._phase == STOP

    @property
    def latest(self) -> Setpoint | None:
        slot = self._slot
        return slot[0] if slot is not None else None

    def stamp(self, sp: Setpoint) -> None:
        """The loop hands over ``sp`` now."""
        self._slot = (sp, self._clock())

    def outgoing(self) -> Setpoint | None:
        """What to send at this slot (None before the loop's first setpoint)."""
        slot = self._slot
        if slot is None:
            return None
        previous = self._seen
        self._slots = self._slots + 1 if slot is previous else 0
        self._seen = slot
        sp, stamped = slot
        age = self._clock() - stamped
        phase = STOP if self._phase == STOP else (stale_phase(age, self._slots, self.policy) if sp[3] > 0 else FRESH)
        if phase == HOLD and self._operator_stop:
            phase = STOP
        if phase != self._phase:
            was = self._phase
            self._change(phase, age)
            if was == HOLD and self._phase == FRESH and previous is not None:
                self._tell(RESUMED, stamped - previous[1])  # how long the loop was gone
        if self._phase == STOP:
            return ZERO
        if self._phase == HOLD:
            level = self._level_thrust
            return hold_setpoint(sp, self._hold_thrust if level is None else level)
        return sp

    def stop_signal(self, count: int) -> None:
        """The ``count``-th stop signal of the flight: the second one during a stall stops the motors
        now (the stalled loop cannot); otherwise the loop's supervisor acts on it."""
        if count >= STOP_SIGNALS_DURING_STALL and self._phase == HOLD:
            slot = self._slot
            self._change(STOP, self._clock() - slot[1] if slot is not None else math.nan)

    def operator_stop(self) -> None:
        """An operator's stop (any thread): the loop's supervisor acts on it at its next tick; while
        the loop is stalled (a hold, or from the slot a hold would start), the motors stop now."""
        self._operator_stop = True
        if self._phase == HOLD:
            slot = self._slot
            self._change(STOP, self._clock() - slot[1] if slot is not None else math.nan)

    def _change(self, phase: str, age: float) -> None:
        with self._lock:
            if self._phase == STOP or phase == self._phase:
                return
            self._phase = phase
            if phase == HOLD:
                self.holds += 1
            elif phase == STOP:
                self.stops += 1
        if phase != FRESH:
            self._tell(phase, age)

    def _tell(self, what: str, age: float) -> None:
        listener = self._listener
        if listener is not None:
            try:
                listener(what, age)
            except Exception:  # noqa: BLE001 - the radio must go on sending whatever the listener does
                pass


__all__ = ["FRESH", "HOLD", "RESUMED", "STOP", "Setpoint", "StaleGuard", "StalePolicy", "ZERO", "hold_setpoint", "stale_phase"]
