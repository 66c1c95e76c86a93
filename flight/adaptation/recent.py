"""The ticks a model swap re-bases the layer's offset over (``FastAdaptation.rebase``).

Per tick: the measured state, the command as flown, the flying model's acceleration for it, and where the
drone above was when the model was evaluated (a fleet model's neighbour input, docs/fleet.md#neighbour-input;
NaN without one). A new model is judged on the same ticks at the same neighbour positions: evaluated at its
stand-in instead, a model of the wake predicted its peak on every tick, and the re-base moved that peak into
the layer's constant.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Recent(NamedTuple):
    x: np.ndarray  # (n, 6) measured states
    u: np.ndarray  # (n, 3) commands as flown
    a: np.ndarray  # (n, 3) the flying model's acceleration for them
    neighbour: np.ndarray  # (n, 3) the drone above's world position the model saw; NaN rows: none given


class RecentTicks:
    """A ring of the newest ``capacity`` ticks (order does not matter: a re-base takes their mean)."""

    def __init__(self, capacity: int) -> None:
        self._x = np.zeros((capacity, 6))
        self._u = np.zeros((capacity, 3))
        self._a = np.zeros((capacity, 3))
        self._nb = np.full((capacity, 3), np.nan)
        self._len = 0
        self._i = 0

    def __len__(self) -> int:
        return self._len

    def reset(self) -> None:
        self._len = self._i = 0

    def add(self, x: np.ndarray, u: np.ndarray, a: np.ndarray, neighbour: np.ndarray | None) -> None:
        i = self._i
        self._x[i], self._u[i], self._a[i] = x, u, a
        self._nb[i] = np.nan if neighbour is None else neighbour
        self._i = (i + 1) % self._x.shape[0]
        self._len = min(self._len + 1, self._x.shape[0])

    def view(self) -> Recent:
        n = self._len
        return Recent(self._x[:n].copy(), self._u[:n].copy(), self._a[:n].copy(), self._nb[:n].copy())

    def set_accelerations(self, a: np.ndarray) -> None:
        """The model now flying, on the same ticks: later re-bases compare against it."""
        self._a[: a.shape[0]] = a


__all__ = ["Recent", "RecentTicks"]
