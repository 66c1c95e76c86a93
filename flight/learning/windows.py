"""Online learning's data windows (the paper's Algorithm 1): airborne MPC ticks cut into windows of ``t_col``.

A swap or rollback discards the partial window, so every window was flown under one model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from cfknode.flight.adaptation.loop import GROUND_MARGIN, body_z
from cfknode.flight.learning.command_lag import CommandLag
from cfknode.flight.neighbours import NONE_ABOVE
from cfknode.models.input_layouts import NEIGHBOUR_SCALE_FLOOR, about_the_axis
from cfknode.models.trainer_process import Window

# Same rules as offline training data (cfknode.app.logs.training_data, which imports torch through its Segment):
# by default ground effect and contact are not the model's business; online.min_height lowers the floor for a flight
# meant to learn ground effect.
MIN_HEIGHT = 0.1  # m above the ground
ELIGIBLE_SOURCES = ("mpc",)  # ticks the MPC flew with the model; fallback ticks were not
# A window over which the fast layer's mass estimate moved more than this (relative) is the layer's transient,
# not the model's error: a network trained on it holds part of the mass the layer is still learning, and the two
# then share it (thrust map -15 %: the mass stalled at 1.06 of nominal instead of 1.18, 5x the layer's MSE).
SETTLING_SPAN = 0.01
KEEP_S = 4.0  # s of ticks kept (at least three windows): the gate's fresh data and the monitor's window come from them


# The supervisor states a wake-only recorder learns in ("": a loop without a supervisor). In a take-off or a
# landing the drone's own climb and the floor change its force while the drone above seems to move with them:
# a stacked pair's first network, fitted on the take-off, flew 1.07-1.31x the layer alone.
WAKE_STATES = ("", "TRACK")


@dataclass(frozen=True)
class WakeOnly:
    """A recorder for networks that see the neighbour alone (fleet.wake_only)."""

    gravity: float  # m/s^2 (vehicle.gravity)
    per_cmd: float  # m/s^2 per unit of the RPYT thrust command at the nominal mass (newton_per_cmd / mass)


def flown_command(thrust_cmd: float, q: np.ndarray, wake: WakeOnly) -> np.ndarray:
    """The acceleration the thrust sent gives a vehicle of the nominal mass along its measured attitude ``q``
    (w, x, y, z), gravity included: what a wake-only recorder records as the command.

    A network of the neighbour alone learns whatever the command leaves, so the command must hold what the drone
    itself did. The MPC's command misses two things. The layer's thrust scale s: the Mellinger layer sends s times
    the thrust asked for, and a layer that took the wake's mean for a mass (s 1.06-1.3 after passes under a drone
    0.2 m above) left (s - 1)(u + g), 0.5-1.6 m/s^2, where there is no wake; the networks learned it as the jet's
    far field. And the attitude loop's lag: at a line's end at 1 m/s the tilt lags the command, and the vertical
    share of the thrust with it; a network learned +4 m/s^2 there, and its swap ended a flight with the
    separation guard."""
    a = (thrust_cmd * wake.per_cmd) * body_z(q)
    a[2] -= wake.gravity
    return a


class TickLike(Protocol):
    t: float
    est: Any
    acc: np.ndarray
    setpoint: Any  # the AttitudeSetpoint sent: its thrust command is a wake-only recorder's (flown_command)
    source: str
    model_version: int
    compute_s: float


class WindowRecorder:
    """Cuts the run of eligible ticks into windows of ``t_col``; keeps the run for the gate.

    A *run* is the newest contiguous stretch of eligible ticks under one model; anything else
    (on the ground, a fallback tick, another model version, ``reset``) ends it and discards the
    partial window. Storage is preallocated (``KEEP_S`` of ticks, or three windows); adding a tick is a few
    array stores.
    """

    def __init__(
        self, t_col: float, rate_hz: float, start_time: float = 0.0, ground_z: float | None = None,
        min_height: float = MIN_HEIGHT, neighbour: Any = None, wake_only: WakeOnly | None = None,
        command_lag_s: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        """``ground_z``: the floor's height; ticks within ``min_height`` of it are not recorded
        (None: no floor rule, for a flight that starts in the air or a plant without ground).
        ``neighbour``: a fleet drone's ``NeighbourFeed`` (flight/neighbours.py): each tick also records the
        relative position of the drone above, and windows carry it (``Window.nb``); None: not recorded.
        ``wake_only``: the networks see that position alone (fleet.wake_only), so the layer's step alarms and its
        moving thrust scale cut no window: a pass under the drone above is what the layer takes for a step (30 of
        41 windows of a crossing were dropped as unsettled), and a network of the neighbour's position alone cannot
        hold the layer's mass. Its commands are what the thrust sent did (``flown_command``), and it learns while
        the supervisor tracks alone (``WAKE_STATES``). None: not wake-only.
        ``command_lag_s``: (x/y, z) lags the commands act through (``CommandLag``); the recorded command is the
        lagged one. (0, 0): as sent."""
        self.t_col = t_col
        self.start_time = start_time
        # A longer gap between ticks (flown blind, or by another controller) ends the run; lockstep
        # ticks land on the plant's 2 ms grid, so neighbours can be up to two plant steps apart.
        self._max_gap = 3.0 / rate_hz
        cap = int(math.ceil(max(KEEP_S, 3.0 * t_col) * rate_hz)) + 8
        self._t = np.empty(cap)
        self._x = np.empty((cap, 6))
        self._u = np.empty((cap, 3))
        self._s = np.ones(cap)  # the fast layer's thrust scale at each tick
        self._held = np.zeros(cap, dtype=bool)  # the fast layer held near the floor (measured nothing) at this tick
        self._neighbour = neighbour
        self._nb = np.zeros((cap, 3)) if neighbour is not None else None
        self._n = 0  # ticks in the run buffer
        self._w0 = 0  # first tick of the current window in the buffer
        self._version: int | None = None
        self._ground = ground_z
        self._wake = wake_only
        self._lag = CommandLag(command_lag_s, self._max_gap) if any(x > 0.0 for x in command_lag_s) else None
        self._min_height = min_height
        self.windows = 0  # windows completed
        self.discarded = 0  # partial windows thrown away (swap, rollback, run broken)
        self.unsettled = 0  # full windows not trained on: the fast layer's mass was still moving (SETTLING_SPAN)
        self.last_added = False  # whether the newest tick joined the run (the model monitor follows the run)

    def add(self, tick: TickLike) -> Window | None:
        """Record one tick; returns a window when this tick completes one."""
        self.last_added = False
        est = tick.est
        layer = getattr(tick, "layer", None)  # the fast layer's estimate (None without a layer)
        if est is None:
            self._break()
            return None
        # Every tick's command goes through the lag, recorded or not (the motors lag them all); without a lag the
        # command is read only for the ticks recorded.
        u = self._lag(tick.t, self._command(tick)) if self._lag is not None else None
        if (
            tick.source not in ELIGIBLE_SOURCES
            # A tick cut by the thrust clamp or the tilt limit is the limit's motion, not the model's: never trained on.
            or getattr(tick, "saturated", False)
            or (layer is not None and layer.stepping and self._wake is None)  # the layer is tracking a step
            or (self._wake is not None and getattr(tick, "supervisor_state", "") not in WAKE_STATES)
            or tick.t < self.start_time
            or (self._ground is not None and est.p[2] <= self._ground + self._min_height)
            or (self._n > 0 and tick.t - self._t[self._n - 1] > self._max_gap)
        ):
            self._break()
            return None
        if self._version is not None and tick.model_version != self._version:
            self._break()  # defensive: the learner resets on its own swaps; anyone else's also ends the run
        if self._n == self._t.shape[0]:
            self._compact()
        i = self._n
        self._t[i] = tick.t
        self._x[i, 0:3] = est.p
        self._x[i, 3:6] = est.v
        self._s[i] = layer.thrust_scale if layer is not None else 1.0
        self._u[i] = u if u is not None else self._command(tick)
        # Only the floor's hold: a stale pose also freezes the layer, but for a moment, not where it flies.
        self._held[i] = (layer is not None and layer.frozen and self._ground is not None
                         and est.p[2] <= self._ground + GROUND_MARGIN)
        if self._nb is not None:
            self._nb[i] = self._neighbour.relative(est.p)
        if not (math.isfinite(self._x[i].sum()) and math.isfinite(self._u[i].sum())):
            self._break()
            return None
        self._version = tick.model_version
        self._n = i + 1
        self.last_added = True
        if tick.t - self._t[self._w0] < self.t_col - 1e-9:
            return None
        w0, self._w0 = self._w0, self._n
        scale = self._s[w0 : self._n]
        if self._wake is None and float(scale.max() - scale.min()) > SETTLING_SPAN * float(scale.min()):
            self.unsettled += 1
            return None
        self.windows += 1
        nb = self._nb[w0 : self._n].copy() if self._nb is not None else None
        return Window(self.windows, self._t[w0 : self._n].copy(), self._x[w0 : self._n].copy(),
                      self._u[w0 : self._n].copy(), tick.model_version, nb)

    def _command(self, tick: TickLike) -> np.ndarray:
        """The tick's command as this recorder reads it: the MPC's, or for a wake-only one what the thrust sent did."""
        return tick.acc if self._wake is None else flown_command(tick.setpoint.thrust, tick.est.q, self._wake)

    def reset(self) -> None:
        """A model change: the partial window (flown under the old model) is discarded."""
        self._break()

    def count_after(self, after: float) -> int:
        """How many of the run's ticks have t > ``after``."""
        return self._n - int(np.searchsorted(self._t[: self._n], after, side="right"))

    def held_share(self, after: float) -> float:
        """The share of the run's ticks with t > ``after`` on which the fast layer measured nothing (0 without any)."""
        k = int(np.searchsorted(self._t[: self._n], after, side="right"))
        return float(np.mean(self._held[k : self._n])) if self._n > k else 0.0

    def fresh(self, after: float) -> tuple[np.ndarray, ...]:
        """Copies of the run's ticks with t > ``after`` (all flown under the current model): (t, x, u), and the
        neighbour's relative position when recorded."""
        k = int(np.searchsorted(self._t[: self._n], after, side="right"))
        out = (self._t[k : self._n].copy(), self._x[k : self._n].copy(), self._u[k : self._n].copy())
        return out if self._nb is None else (*out, self._nb[k : self._n].copy())

    @property
    def last_u(self) -> np.ndarray | None:
        """The newest recorded tick's command as recorded (see ``add``); None: no tick."""
        return self._u[self._n - 1] if self._n > 0 else None

    @property
    def last_nb(self) -> np.ndarray | None:
        """The newest recorded tick's neighbour relative position (None: not recorded, or no tick)."""
        return self._nb[self._n - 1] if self._nb is not None and self._n > 0 else None

    def _break(self) -> None:
        if self._n > self._w0:
            self.discarded += 1
        self._n = self._w0 = 0
        self._version = None

    def _compact(self) -> None:
        # Keep the newest half (always more than the current window, as capacity >= 3 t_col).
        keep = min(self._n - self._w0 + self._t.shape[0] // 2, self._n)
        start = self._n - keep
        self._t[:keep] = self._t[start : self._n]
        self._x[:keep] = self._x[start : self._n]
        self._u[:keep] = self._u[start : self._n]
        self._s[:keep] = self._s[start : self._n]
        self._held[:keep] = self._held[start : self._n]
        if self._nb is not None:
            self._nb[:keep] = self._nb[start : self._n]
        self._w0 -= start
        self._n = keep


def nothing_to_learn_above(windows: tuple[Window, ...]) -> str:
    """Why a wake-only round on these windows would learn nothing, as the summary's count names it; "" if it can.

    ``windows_no_drone_above``: no drone was above at any tick (the neighbour input always ``NONE_ABOVE``, or not
    recorded), a fleet's top drone. ``windows_one_point_above``: the drone above stayed at one point of its wake
    (its horizontal distance and height, as the networks see them, each within ``NEIGHBOUR_SCALE_FLOOR``), a stacked
    pair on one pattern. A network of the neighbour alone then learns a constant the fast layer holds, and
    extrapolates it: when the drone above flies off, it predicts the wake still on. Skipped rounds also leave the
    shared trainer to the drones below (docs/fleet.md#wake-only)."""
    rows = [w.nb for w in windows if w.nb is not None]
    if not any(np.any(nb != NONE_ABOVE) for nb in rows):
        return "windows_no_drone_above"
    seen = about_the_axis(np.concatenate(rows))
    if len(rows) == len(windows) and np.all(np.ptp(seen, axis=0) < NEIGHBOUR_SCALE_FLOOR):
        return "windows_one_point_above"
    return ""


__all__ = ["ELIGIBLE_SOURCES", "MIN_HEIGHT", "TickLike", "WindowRecorder", "nothing_to_learn_above"]
