"""The supervisor's vocabulary: its states, what it reads and reports, and its timing constants."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Any, Callable, Protocol

import numpy as np

from cfknode.kernel.setpoint import AttitudeSetpoint
from cfknode.safety.watchdogs import LinkSource

MOTORS_OFF = AttitudeSetpoint(0.0, 0.0, 0.0, 0)
FLY, BLIND, OFF = "fly", "blind", "off"
# Zeros streamed after the motors are cut, before the radio's hand-back: briefly after a
# landing (as the flight loop always did), longer after a stop so the log shows the fall.
CUTOFF_HOLD_S = 0.2
STOP_HOLD_S = 1.0
# A flight that has not ended this long after its trajectory is stopped (it cannot happen
# with the landing rules below; this bounds the loop whatever happens).
MAX_OVERTIME_S = 30.0
# Slow inputs are read on a 40-tick cycle (0.1 s at 400 Hz), at most one per tick so that no
# tick pays for two: the link every 10 ticks, the battery every 20, the /safety status once.
_CYCLE = 40
_SCHEDULE = {0: "battery", 5: "link", 10: "status", 15: "link", 20: "battery", 25: "link", 35: "link"}
# The start pose must be this close to level to take off.
MAX_START_TILT_DEG = 20.0
TOUCHDOWN_S = 0.1
_TIME_EPS = 1e-9


class State(str, Enum):
    IDLE = "IDLE"
    PREFLIGHT = "PREFLIGHT"
    TAKEOFF = "TAKEOFF"
    TRACK = "TRACK"
    LAND = "LAND"
    LANDED = "LANDED"
    EMERGENCY = "EMERGENCY"


_FLYING = frozenset({State.TAKEOFF, State.TRACK, State.LAND})
_STOP, _LAND = "stop", "land"
_NOTE = "note"  # an operator-request queue entry that is only logged
# What the loop asks of ``internal_error``: land, stop the motors, or only record it.
ERROR_LAND, ERROR_STOP, ERROR_RECORD = _LAND, _STOP, "record"


class Radio(Protocol):
    def set_setpoint(self, sp: AttitudeSetpoint) -> None: ...

    def set_extpose(self, position: np.ndarray, quaternion: np.ndarray) -> None: ...

    def pump(self, now: float) -> None: ...


class Log(Protocol):
    def write(self, topic: str, t: float, msg: dict[str, Any]) -> None: ...


@dataclass(frozen=True)
class SupervisorInputs:
    """Where the supervisor reads what the loop does not hand it.

    ``battery_voltage()``: volts or None when unknown (simulator: ``sim.battery_voltage``;
    hardware: ``pm.vbat`` telemetry). ``link_status(now)``: see ``watchdogs.LinkStatus``.
    """

    battery_voltage: Callable[[], float | None] | None = None
    link_status: LinkSource | None = None


@dataclass(frozen=True)
class SupervisedFlight:
    """The flight a supervisor watches over."""

    trajectory: Any  # a kernel Reference: its segments, duration and samples
    vehicle: Any  # a VehicleConfig: the blind hold's thrust
    rate_hz: float  # the loop's tick rate
    deadlines_apply: bool  # act on missed deadlines and slow solves (wall clock only)
    robot: str = ""  # the rigid body's name, for messages


@dataclass(frozen=True)
class Outcome:
    """How the flight ended: the final state, one line for the user, and the cause."""

    state: State
    message: str
    cause: str  # "complete", or the code of what landed/stopped/refused it
    t: float  # flight time the cause fired (NaN for a complete flight)
    errors: tuple[str, ...] = ()  # one line per distinct internal error (their tracebacks are in the log)


@dataclass(frozen=True)
class SafetySnapshot:
    """The supervisor's readings, for a dashboard (never for control)."""

    state: State
    cause: str
    pose_age_s: float
    fence_margin_m: float
    tracking_error_m: float
    battery_v: float
    link_silence_s: float
    fallback_run: int  # MPC failures in a row
