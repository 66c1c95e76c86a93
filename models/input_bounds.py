"""Where each network of a queue saw data: its inputs' range, stored with the model, and held to in flight.

A network fitted on a take-off (horizontal speed about 0) says nothing about a circle at 0.4 m/s, yet it
returns something there: slopes in v_x and v_y that no data constrained. Flown on the circle, such a
model made the default mission 16 % worse beside the fast layer while it scored as well as the flying
one on the data it was judged on (docs/design.md#online-learning). With bounds, a network's inputs are
clamped to the range it was trained on, widened a little: outside it the network holds the value at the
edge (no slope), and the fast layer takes what is left.

The bounds live in the model file's metadata (``extra.input_bounds``: per network ``[low, high]``, each a
list of the input's numbers, or null for a network stored without them), oldest network first as the
queue. Plain numbers only: no pickled objects.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from cfknode.models.residual_check import finite_numbers

BOUNDS_KEY = "input_bounds"
WIDEN = 0.25  # of the data's own range, on each side
# ... plus, per input, at least this much on each side: v (m/s), u (m/s^2), the neighbour's offset (m)
FLOOR_V, FLOOR_U, FLOOR_D = 0.05, 0.2, 0.05


def data_bounds(z: np.ndarray) -> tuple[list[float], list[float]]:
    """The bounds of one network from its training inputs ``z`` (n, 6 or 9): (v, u[, d]) over the data,
    widened by ``WIDEN`` of the range and at least the floors."""
    lo, hi = z.min(axis=0), z.max(axis=0)
    floors = np.array([FLOOR_V] * 3 + [FLOOR_U] * 3 + [FLOOR_D] * (z.shape[1] - 6))
    pad = np.maximum(WIDEN * (hi - lo), floors)
    return [float(v) for v in lo - pad], [float(v) for v in hi + pad]


def queue_bounds(base_extra: Mapping[str, Any] | None, base_networks: int, new: tuple[list[float], list[float]],
                 networks: int) -> list[list[list[float]] | None]:
    """The bounds of a queue of ``networks`` networks: the base queue's (null where it stored none) and the new
    network's, newest last, the oldest dropped as the queue drops them."""
    old = base_extra.get(BOUNDS_KEY) if isinstance(base_extra, Mapping) else None
    if old is None or bounds_problem(old, base_networks) is not None:
        old = [None] * base_networks
    return [*old, [new[0], new[1]]][-networks:]


def bounds_problem(value: object, networks: int) -> str | None:
    """Why stored bounds are unusable (None when absent or well formed for ``networks`` networks)."""
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != networks:
        return f"metadata 'extra.{BOUNDS_KEY}' must list one entry per network ({networks})"
    for entry in value:
        if entry is None:
            continue
        if not (isinstance(entry, list) and len(entry) == 2 and all(finite_numbers(side) for side in entry)
                and len(entry[0]) == len(entry[1]) and all(a <= b for a, b in zip(*entry))):
            return f"metadata 'extra.{BOUNDS_KEY}': each entry must be null or [low, high], finite, low <= high"
    return None


def stored_bounds(extra: object, networks: int) -> np.ndarray | None:
    """(networks, 2, n_in) bounds, +-inf for a network stored without them; None when the file has none."""
    value = extra.get(BOUNDS_KEY) if isinstance(extra, Mapping) else None
    if value is None or networks == 0 or bounds_problem(value, networks) is not None:
        return None
    width = max((len(e[0]) for e in value if e is not None), default=0)
    if width == 0:
        return None
    out = np.empty((networks, 2, width))
    out[:, 0], out[:, 1] = -np.inf, np.inf
    for j, entry in enumerate(value):
        if entry is not None and len(entry[0]) == width:
            out[j] = np.asarray(entry, dtype=np.float64)
    return out


__all__ = ["BOUNDS_KEY", "bounds_problem", "data_bounds", "queue_bounds", "stored_bounds"]
