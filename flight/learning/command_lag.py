"""The command as it acts: the recorded commands through the attitude loop's and the motors' first-order lags.

The learner's target is the measured acceleration minus the command. A command acts through the motors' lag
(vertical, ~15 ms) and the attitude loop's (horizontal); measured against the command as sent, the lag shows as a
force proportional to the command's rate. On a vertical oscillation that rate follows the velocity, and the
motors' lag (+0.25 v_z at 0.65 Hz) cancelled most of the thrust lost with climb rate (-0.4 v_z) in every window:
no network the gate kept learned the inflow (docs/results.md). Pure floats: this runs every tick.
"""

from __future__ import annotations

import math

import numpy as np


class CommandLag:
    """A first-order lag per axis (x/y share one time constant); a gap longer than ``max_gap`` s restarts it."""

    def __init__(self, lag_s: tuple[float, float], max_gap: float) -> None:
        xy, z = float(lag_s[0]), float(lag_s[1])
        self._tau = (xy, xy, z)
        self._max_gap = max_gap
        self._y = [0.0, 0.0, 0.0]
        self._t: float | None = None
        self._dt = math.nan  # the last step's dt, and its factors (ticks come at one rate: computed once per rate)
        self._alpha = (1.0, 1.0, 1.0)

    def __call__(self, t: float, u: np.ndarray) -> np.ndarray:
        """The command ``u`` (m/s^2) sent at ``t`` (s), as it acts: the lagged command after this tick."""
        y = self._y
        if self._t is None or not 0.0 < t - self._t <= self._max_gap:
            y[0], y[1], y[2] = float(u[0]), float(u[1]), float(u[2])
        else:
            dt = t - self._t
            if dt != self._dt:
                self._dt = dt
                self._alpha = tuple(1.0 - math.exp(-dt / tau) if tau > 0.0 else 1.0 for tau in self._tau)
            a = self._alpha
            y[0] += a[0] * (float(u[0]) - y[0])
            y[1] += a[1] * (float(u[1]) - y[1])
            y[2] += a[2] * (float(u[2]) - y[2])
        self._t = t
        return np.array(y)


def lagged_commands(t: np.ndarray, u: np.ndarray, lag_s: tuple[float, float]) -> np.ndarray:
    """A recorded run's commands (``u``'s first three columns; any others, such as a neighbour's position, are
    kept) as they acted, by ``CommandLag``: what offline training measures its targets against, as the
    recorder does in flight. A gap of three sample periods restarts the lag."""
    out = np.array(u, dtype=float)
    if out.shape[0] == 0 or not any(x > 0.0 for x in lag_s):
        return out
    dt = np.diff(t)
    lag = CommandLag(lag_s, 3.0 * float(np.median(dt)) if dt.size else math.inf)
    for i in range(out.shape[0]):
        out[i, :3] = lag(float(t[i]), out[i, :3])
    return out


__all__ = ["CommandLag", "lagged_commands"]
