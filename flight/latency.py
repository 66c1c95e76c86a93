"""Prediction across the command path: plan from where the vehicle will be when the command acts.

A command sent at t reaches the motors' thrust only after the radio hold (up to one
``radio.tx_rate_hz`` period), the firmware's attitude loop and the motor lag: together about
``estimator.command_delay`` seconds. Over [t, t + delay] the vehicle therefore flies the
commands already sent in [t - delay, t), which are known, so the state at t + delay is a
kinematic prediction from the estimate at t (a Smith predictor on the translational model).

The commands are not all the vehicle flies: the rotor drag (0.25 m/s^2 per m/s) and whatever the
fast layer leaves act too, and a prediction on the commands alone is off by them times the delay
(on the slow default circle that made the MPC's error 5x larger, docs/history.md). With
``estimator.command_residual_tau`` the predictor measures that part over the last delay (the
estimate's velocity change less the commands' share) and predicts with it, low-passed.

A tilt does not arrive after a delay but through the attitude loop's lag (63 % after ~0.15 s); with
``estimator.command_lag`` the horizontal prediction relaxes the acting acceleration toward the newest
command over ``command_delay`` instead. The vertical path is the motors' alone (~16 ms):
``estimator.command_delay_z`` gives it its own, shorter delay.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from typing import Any

import numpy as np


def held_increments(times: np.ndarray, accs: np.ndarray, a: float, b: float) -> tuple[np.ndarray, np.ndarray]:
    """Over [a, b] of commands held from ``times[k]`` to ``times[k+1]`` (the last one on): the velocity
    gained, the integral of acc, and the position the same accelerations give if flown from ``a``,
    the integral of (b - s) acc(s). Before ``times[0]`` nothing is known: zero (coast)."""
    if len(times) == 0 or b <= a:
        return np.zeros(3), np.zeros(3)
    lo = np.maximum(times, a)
    hi = np.minimum(np.append(times[1:], b), b)
    h = np.maximum(hi - lo, 0.0)
    # The integral of (b - s) over [lo, hi]: h times (b - midpoint); vectorised, it runs every tick.
    return h @ accs, (h * (b - 0.5 * (lo + hi))) @ accs


def lag_increments_xy(ax: float, ay: float, ux: float, uy: float, tau: float,
                      h: float) -> tuple[float, float, float, float]:
    """Over ``h`` s of an x/y acceleration relaxing from (ax, ay) toward the held (ux, uy) with time constant
    ``tau``: the velocity and the position gained from rest (exact for the first-order lag), as dv_x, dv_y, dp_x,
    dp_y. On Python floats: it runs every tick, and numpy's per-call cost on two numbers was most of its time."""
    k = -math.expm1(-h / tau)  # 1 - exp(-h / tau)
    tk, c, e = tau * k, 0.5 * h * h, tau * (h - tau * k)
    return ux * h + (ax - ux) * tk, uy * h + (ay - uy) * tk, ux * c + (ax - ux) * e, uy * c + (ay - uy) * e


def unexplained_acceleration(v_now: np.ndarray, v_then: np.ndarray, flown_dv: np.ndarray, span: float) -> np.ndarray:
    """The mean acceleration over ``span`` seconds the commands do not account for (drag, the layer's rest)."""
    return (np.asarray(v_now, float) - np.asarray(v_then, float) - flown_dv) / span


class CommandDelayPredictor:
    """Keeps the commands of the last delays; ``ahead`` shifts an estimate across the command path.

    ``delay`` is the horizontal axes' (and the vertical's unless ``delay_z`` is given); the vertical
    path has no attitude loop, only the motors, so it is an order shorter. The estimate ``ahead``
    returns is stamped ``est.t + delay``: with a shorter vertical delay the vertical state is the one
    predicted at ``est.t + delay_z``, which the caller takes as the vertical error that far ahead.
    ``residual_tau`` > 0: correct the prediction by the low-passed unexplained acceleration.
    """

    def __init__(self, delay: float, delay_z: float | None = None, residual_tau: float = 0.0,
                 lag: float = 0.0) -> None:
        if min(delay, residual_tau, lag) < 0.0 or (delay_z is not None and delay_z < 0.0):
            raise ValueError(f"command delays, lag and residual_tau must be >= 0 s, got "
                             f"{delay}, {delay_z}, {lag}, {residual_tau}")
        self.delay = delay
        self.delay_z = delay if delay_z is None else delay_z
        self.residual_tau = residual_tau
        # lag > 0: x and y fly the commands through a first-order lag (the attitude loop), not a delay.
        self.lag = lag
        self._flown = (0.0, 0.0)  # the lagged acceleration at ``_flown_t``, x and y
        self._flown_t: float | None = None
        self._flown_sum = (0.0, 0.0)  # its integral since the first command (the residual's model share)
        self._sent: deque[tuple[float, np.ndarray]] = deque()
        # (t, v, the lagged acceleration's integral) at each estimate ``ahead`` was given
        self._seen: deque[tuple[float, np.ndarray, tuple[float, float]]] = deque()
        self.residual = np.zeros(3)
        self._residual_t: float | None = None
        self._u_xy = (0.0, 0.0)  # the newest command's x and y (the lag's target)
        self._retime()

    def retune(self, delay: float, lag: float, residual_tau: float, residual: Any = None) -> None:
        """Predict over ``delay`` through ``lag`` from now on (the vertical at once): an identified attitude loop's
        lag (flight/learning/attitude_lag.py). What was kept under the old settings is dropped. ``residual``: the
        unexplained acceleration (x, y) to start from, the fast layer's offset, an estimate of the same force;
        started at zero instead, a wind's 0.3 m/s^2 is missing from the plan for the first delay and its low-pass,
        and the switch costs more than planning ahead gains on a slow circle (docs/results.md)."""
        if min(delay, lag, residual_tau) < 0.0:
            raise ValueError(f"command delay, lag and residual_tau must be >= 0 s, got {delay}, {lag}, {residual_tau}")
        self.delay, self.delay_z, self.lag, self.residual_tau = delay, 0.0, lag, residual_tau
        self.reset()
        self._retime()
        if residual is not None and residual_tau > 0.0:
            self.residual = np.array([float(residual[0]), float(residual[1]), 0.0])

    def _retime(self) -> None:
        """The axis groups with a delay, kept: they change only with the settings (``retune``)."""
        self._active_groups = [g for g in self._groups() if g[0] > 0.0]
        self._any_held = any(not lagged for _, _, lagged in self._active_groups)

    @property
    def active(self) -> bool:
        return self.delay > 0.0 or self.delay_z > 0.0

    def _delays(self) -> np.ndarray:
        return np.array([self.delay, self.delay, self.delay_z])

    def reset(self) -> None:
        self._sent.clear()
        self._seen.clear()
        self.residual = np.zeros(3)
        self._residual_t = None
        self._flown = (0.0, 0.0)
        self._flown_t = None
        self._flown_sum = (0.0, 0.0)

    def _relax(self, t: float) -> None:
        """Bring the lagged acceleration to ``t`` under the newest command sent."""
        if self.lag <= 0.0 or self._flown_t is None or t <= self._flown_t or not self._sent:
            return
        (fx, fy), (ux, uy), h = self._flown, self._u_xy, t - self._flown_t
        dvx, dvy, _, _ = lag_increments_xy(fx, fy, ux, uy, self.lag, h)
        self._flown_sum = (self._flown_sum[0] + dvx, self._flown_sum[1] + dvy)
        e = math.exp(-h / self.lag)
        self._flown = (ux + (fx - ux) * e, uy + (fy - uy) * e)
        self._flown_t = t

    def note(self, t: float, acc: np.ndarray) -> None:
        """The command sent at ``t`` (held until the next one)."""
        if not self.active:
            return
        self._relax(t)
        if self._flown_t is None:
            self._flown_t = t
        command = np.array(acc, dtype=float)
        self._sent.append((t, command))
        self._u_xy = (float(command[0]), float(command[1]))
        # Keep the newest command sent at or before t - reach: it is still acting then.
        reach = max(self.delay, self.delay_z) * (2.0 if self.residual_tau > 0.0 else 1.0)
        while len(self._sent) > 1 and self._sent[1][0] <= t - reach:
            self._sent.popleft()

    def ahead(self, est: Any) -> Any:
        """``est`` (with t, p, v) moved across the command path under the commands in flight."""
        if not self.active or not self._sent:
            return est
        t = est.t
        # An axis with no delay is neither moved nor corrected (its residual would be added times 0), and with
        # the lag and no held group the commands are not needed as arrays (0.06 ms of a tick's median).
        groups, held = self._active_groups, self._any_held
        times = np.array([s for s, _ in self._sent]) if held else np.empty(0)
        accs = np.array([a for _, a in self._sent]) if held else np.empty((0, 3))
        self._relax(t)
        if self.residual_tau > 0.0:
            self._learn(t, np.asarray(est.v, float), times, accs, groups)
        p = np.array(est.p, dtype=float)
        v = np.array(est.v, dtype=float)
        for d, axes, lagged in groups:
            if lagged:  # x and y: on floats, as numpy would do them element by element
                dvx, dvy, dpx, dpy = lag_increments_xy(*self._flown, *self._u_xy, self.lag, d)
                rx, ry, c = float(self.residual[0]), float(self.residual[1]), 0.5 * d * d
                vx, vy = float(v[0]), float(v[1])
                p[0] += vx * d + dpx + c * rx
                p[1] += vy * d + dpy + c * ry
                v[0] = vx + (dvx + d * rx)
                v[1] = vy + (dvy + d * ry)
                continue
            dv, dp = held_increments(times, accs, t - d, t)
            extra = self.residual[axes]
            p[axes] += v[axes] * d + dp[axes] + 0.5 * d * d * extra
            v[axes] += dv[axes] + d * extra
        return dataclasses.replace(est, t=t + self.delay, p=p, v=v)

    def _groups(self) -> list[tuple[float, np.ndarray, bool]]:
        """Axes sharing a model, as (delay, index array, flown through the lag): with a lag, x and y over the
        horizontal delay through it, z over its own delay."""
        if self.lag > 0.0:
            return [(self.delay, np.array([0, 1]), True), (self.delay_z, np.array([2]), False)]
        return [(d, axes, False) for d, axes in _groups(self._delays())]

    def _learn(self, t: float, v: np.ndarray, times: np.ndarray, accs: np.ndarray,
               groups: list[tuple[float, np.ndarray, bool]]) -> None:
        """Update the unexplained acceleration from the velocity change over the last delay (per axis)."""
        self._seen.append((t, v.copy(), self._flown_sum))
        d_max = max(self.delay, self.delay_z)
        while len(self._seen) > 1 and self._seen[1][0] <= t - d_max:
            self._seen.popleft()
        then_t, then_v, then_sum = self._seen[0]
        span = t - then_t
        if span < d_max or d_max <= 0.0:
            return  # not a whole delay seen yet
        # Over [then_t, t] the vehicle flew the commands sent a delay before (per axis group).
        flown = np.zeros(3)
        for d, axes, lagged in groups:
            if lagged:
                flown[0], flown[1] = self._flown_sum[0] - then_sum[0], self._flown_sum[1] - then_sum[1]
            else:
                flown[axes] = held_increments(times, accs, then_t - d, t - d)[0][axes]
        measured = unexplained_acceleration(v, then_v, flown, span)
        h = t - self._residual_t if self._residual_t is not None else 0.0
        self._residual_t = t
        self.residual = self.residual + (-math.expm1(-h / self.residual_tau)) * (measured - self.residual)


def _groups(delays: np.ndarray) -> list[tuple[float, np.ndarray]]:
    """Axes sharing a delay, as (delay, index array)."""
    return [(float(d), np.flatnonzero(delays == d)) for d in np.unique(delays)]


__all__ = ["CommandDelayPredictor", "held_increments", "lag_increments_xy", "unexplained_acceleration"]
