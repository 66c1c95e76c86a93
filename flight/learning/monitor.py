"""Model monitor: drop a flying KNODE model the world has changed under.

The validation gate judges a candidate once, before it flies. The world can change after
that (the paper's second mass step): a model fitted to half the mass then predicts twice the
thrust the vehicle now gets, and keeping it until the next round is accepted costs a round
trip of flight (window + training + gate, ~0.6 s at the defaults). The monitor checks the
flying model every few ticks against the nominal model on the newest ticks and reports when
the model explains the recent motion clearly worse than no model at all; the learner then
flies nominal until its next accepted candidate.

The statistic is the mean acceleration error over the last ``window_s``:
``((v_end - v_start) - sum_k dt_k f(v_k, u_k)) / T`` with f = u (nominal) or u + r(v, u).
Velocity noise enters only through the two end points, identically for both models, so it
needs no filter and a 0.1 s window resolves a few tenths of a m/s^2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np


class Residual(Protocol):
    def evaluate(self, x: np.ndarray, u: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class MonitorSettings:
    window_s: float  # s of newest ticks judged
    every_ticks: int  # ticks between checks
    margin: float  # drop when error(model) > margin * error(nominal) + floor
    floor: float  # m/s^2: below this a model is never dropped (estimator noise, command lag)


@dataclass(frozen=True)
class MonitorVerdict:
    drop: bool
    error_model: float  # m/s^2, norm of the mean acceleration error
    error_nominal: float
    ticks: int


def mean_acceleration_error(model: Residual | None, t: np.ndarray, v: np.ndarray, u: np.ndarray,
                            nb: np.ndarray | None = None) -> np.ndarray:
    """Mean over [t0, t_end] of measured minus predicted acceleration, (3,); rectangle rule on the ticks.

    Each tick's command is held until the next tick (the loop's zero-order hold). ``nb``: the neighbour's
    relative position at each tick, for a model that takes it (docs/fleet.md#neighbour-input).
    """
    dt = np.diff(t)[:, None]
    f = u[:-1].copy()
    if model is not None:
        x = np.zeros((v.shape[0] - 1, 6))  # the residual is translation invariant: position is not an input
        x[:, 3:6] = v[:-1]
        if nb is not None and getattr(model, "takes_neighbour", False):
            f += model.evaluate(x, u[:-1], nb[:-1])  # type: ignore[call-arg]  # x's position is 0: nb is relative
        else:
            f += model.evaluate(x, u[:-1])
    span = float(t[-1] - t[0])
    return ((v[-1] - v[0]) - np.sum(dt * f, axis=0)) / span


class ModelMonitor:
    """Keeps the newest ``window_s`` of (t, v, u) and judges the flying model every ``every_ticks``."""

    def __init__(self, settings: MonitorSettings, rate_hz: float) -> None:
        self.s = settings
        self._cap = max(3, int(math.ceil(settings.window_s * rate_hz)) + 1)
        self._t = np.empty(self._cap)
        self._v = np.empty((self._cap, 3))
        self._u = np.empty((self._cap, 3))
        self._nb: np.ndarray | None = None  # the neighbour's relative position, once one is given
        self._n = 0  # valid samples (<= cap)
        self._i = 0  # next write position (ring)
        self._since = 0  # ticks since the last check

    def reset(self) -> None:
        """A gap in the eligible ticks: the next window starts afresh."""
        self._n = self._i = self._since = 0

    def add(self, t: float, v: np.ndarray, u: np.ndarray, nb: np.ndarray | None = None) -> bool:
        """Record one tick (``nb``: the neighbour's relative position, when recorded); True when a check is due."""
        self._t[self._i] = t
        self._v[self._i] = v
        self._u[self._i] = u
        if nb is not None:
            if self._nb is None:
                self._nb = np.zeros((self._cap, 3))
            self._nb[self._i] = nb
        self._i = (self._i + 1) % self._cap
        self._n = min(self._n + 1, self._cap)
        self._since += 1
        if self._n < self._cap or self._since < self.s.every_ticks:
            return False
        self._since = 0
        return True

    def judge(self, model: Any | None) -> MonitorVerdict:
        """Compare ``model`` with nominal on the buffered ticks (call when ``add`` says so)."""
        order = np.roll(np.arange(self._cap), -self._i)[-self._n :]
        t, v, u = self._t[order], self._v[order], self._u[order]
        nominal = float(np.linalg.norm(mean_acceleration_error(None, t, v, u)))
        if model is None:
            return MonitorVerdict(False, nominal, nominal, self._n)
        nb = self._nb[order] if self._nb is not None else None
        err = float(np.linalg.norm(mean_acceleration_error(model, t, v, u, nb)))
        drop = not math.isfinite(err) or err > self.s.margin * nominal + self.s.floor
        return MonitorVerdict(drop, err, nominal, self._n)


__all__ = ["ModelMonitor", "MonitorSettings", "MonitorVerdict", "mean_acceleration_error"]
