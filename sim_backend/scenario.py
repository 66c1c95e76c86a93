"""Disturbance scenarios for the simulated Crazyflie: mass changes, drag and wind.

Pure functions of the configuration and the time or velocity; the plant calls them.
"""

from __future__ import annotations

import bisect
from typing import Sequence

from cfknode.sim_backend.settings import Gust, MassChange

# A plant step starting at t_k applies a change scheduled at t_c when t_k >= t_c - TIME_TOL:
# step times are k * dt in binary floating point, so a change "at 2.0 s" must not slip a
# step because 1000 * 0.002 happened to round below 2.0.
TIME_TOL = 1e-9


def mass_at(t: float, nominal_mass: float, changes: Sequence[MassChange]) -> float:
    """True mass [kg] for the plant step starting at ``t``.

    Each change sets the mass to ``factor * nominal_mass`` (factors are relative to the
    nominal mass, not cumulative); the latest change at or before ``t`` wins, ties going to
    the one listed last.
    """
    factor = 1.0
    latest = float("-inf")
    for change in changes:
        if change.t - TIME_TOL <= t and change.t >= latest:
            latest = change.t
            factor = change.factor
    return factor * nominal_mass


def wind_at(t: float, calm: Sequence[float], gusts: Sequence[Gust]) -> Sequence[float]:
    """The air velocity [m/s] for the plant step starting at ``t``: the last listed gust blowing then, else ``calm``.

    A gust blows over [t, t + duration), both ends moved ``TIME_TOL`` earlier (step times are k * dt).
    """
    wind = calm
    for gust in gusts:
        if gust.t - TIME_TOL <= t < gust.t + gust.duration - TIME_TOL:
            wind = gust.wind
    return wind


def drag_force(
    vx: float, vy: float, vz: float, drag: Sequence[float], wind: Sequence[float]
) -> tuple[float, float, float]:
    """Linear aerodynamic drag on the air-relative velocity, world frame [N].

    ``F = -drag * (v - wind)`` per axis; a constant wind therefore pushes a hovering vehicle
    with ``drag * wind``.
    """
    return (
        -drag[0] * (vx - wind[0]),
        -drag[1] * (vy - wind[1]),
        -drag[2] * (vz - wind[2]),
    )


class MassSchedule:
    """``mass_at`` for a plant stepping forward in time: the changes sorted once, and a cursor, so
    a step costs O(1) however long the list (a backward query falls back to a bisection)."""

    def __init__(self, nominal_mass: float, changes: Sequence[MassChange]) -> None:
        # A stable sort keeps the listed order among equal times: the one listed last wins, as in mass_at.
        ordered = sorted(changes, key=lambda c: c.t)
        self._from = [c.t - TIME_TOL for c in ordered]
        self._factor = [c.factor for c in ordered]
        self._nominal = nominal_mass
        self._k = -1  # index of the change in force at the last query (-1: none yet)

    def at(self, t: float) -> float:
        """True mass [kg] for the plant step starting at ``t`` (equal to ``mass_at``)."""
        k = self._k
        if k >= 0 and self._from[k] > t:
            k = bisect.bisect_right(self._from, t) - 1
        while k + 1 < len(self._from) and self._from[k + 1] <= t:
            k += 1
        self._k = k
        return (self._factor[k] if k >= 0 else 1.0) * self._nominal
