"""The neighbour input of a fleet drone's learned model: where the nearest drone above is (docs/fleet.md#neighbour-input).

A drone below another flies in its wake (the realistic plant's downwash: up to 28 % of the weight, in a jet
about 6 cm wide), a force that depends on where the other drone is, not on the drone's own state. With
``fleet.neighbour_input`` each drone's KNODE networks see, beside (v, u), d = p_nb - p: the relative position
(world frame) of the nearest drone above it. The nearest drone *above*, not the nearest neighbour: the wake
acts downward only, so a drone beside or below carries no force, and one 3-vector keeps the network small.
With no drone above, d is ``NONE_ABOVE`` (straight up, at the gap where the wake has died out).

``NeighbourBoard`` holds every drone's latest estimated position, written by a tick observer per drone
(``tap(i)``): the fleet's loops run in one process on one event loop, so the board is a plain object the
fleet flight owns (no global state). ``feed(i)`` is drone i's view: ``relative(p)`` for the learner's
windows, ``horizon(x_nodes)`` for the MPC's linearisation, where the neighbour moves along its own
reference from where it was last seen (a known parameter over the horizon, as the reference is).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

ABOVE_MARGIN = 0.05  # m: a drone counts as above when it is this much higher
NONE_ABOVE = np.array([0.0, 0.0, 1.5])  # d with no drone above: the wake is gone beyond a 1.5 m gap


class NeighbourBoard:
    """Every fleet drone's latest position (and time), and each drone's nearest drone above."""

    def __init__(self, refs: Sequence[Any], period: float, node_dt: float, nodes: int, lead: float = 0.0) -> None:
        """``lead``: s the MPC's first node is ahead of the drone's measured state (``estimator.command_delay``: it
        plans from the state predicted that far ahead), so the drone above is taken that much later too."""
        self._refs = list(refs)
        self._p: list[np.ndarray | None] = [None] * len(self._refs)
        self._t = [0.0] * len(self._refs)
        self.period = period
        self.lead = lead
        self._offsets = node_dt * np.arange(nodes)

    def tap(self, i: int) -> "_BoardTap":
        """The tick observer that writes drone i's position."""
        return _BoardTap(self, i)

    def feed(self, i: int) -> "NeighbourFeed":
        return NeighbourFeed(self, i)

    def update(self, i: int, t: float, p: np.ndarray) -> None:
        self._p[i] = np.array(p, dtype=float)
        self._t[i] = float(t)

    def above(self, i: int, p: np.ndarray) -> int | None:
        """The nearest drone (by distance) more than ``ABOVE_MARGIN`` above ``p``; None: none."""
        best, best_d = None, np.inf
        for j, q in enumerate(self._p):
            if j == i or q is None or q[2] <= p[2] + ABOVE_MARGIN:
                continue
            d = float(np.linalg.norm(q - p))
            if d < best_d:
                best, best_d = j, d
        return best

    def position(self, j: int) -> np.ndarray:
        p = self._p[j]
        assert p is not None
        return p

    def moved(self, j: int, n: int, now: float) -> np.ndarray:
        """Drone j's position at ``now`` + the first ``n`` node offsets: its last position moved along its reference."""
        t0 = self._t[j]
        ref = self._refs[j]
        times = now + self._offsets[:n]
        ps = np.asarray(ref.sample(np.concatenate(([t0], times))).p, dtype=float)
        return self.position(j) + (ps[1:] - ps[0])


class NeighbourFeed:
    """Drone i's neighbour input: the nearest drone above, now and over the MPC's horizon."""

    def __init__(self, board: NeighbourBoard, i: int) -> None:
        self._board = board
        self.index = i
        self.lead: float | None = None  # s the plan leads this drone's measured state (None: the board's)

    def relative(self, p: np.ndarray) -> np.ndarray:
        """d = p_nb - p (3,) for a drone at ``p``; ``NONE_ABOVE`` with no drone above."""
        j = self._board.above(self.index, p)
        return NONE_ABOVE.copy() if j is None else self._board.position(j) - p

    def above(self, p: np.ndarray) -> np.ndarray | None:
        """The nearest drone above ``p``: its world position, None with none."""
        j = self._board.above(self.index, p)
        return None if j is None else self._board.position(j)

    def horizon(self, x_nodes: np.ndarray, measured: bool = False) -> np.ndarray | None:
        """The neighbour's world position at each node (N, 3), from this tick (plus the plan's lead) on; None with no
        drone above. ``measured``: the nodes start at the measured state (no lead)."""
        j = self._board.above(self.index, x_nodes[0, 0:3])
        if j is None:
            return None
        b = self._board
        lead = b.lead if self.lead is None else self.lead
        return b.moved(j, x_nodes.shape[0], b._t[self.index] + b.period + (0.0 if measured else lead))


class _BoardTap:
    def __init__(self, board: NeighbourBoard, i: int) -> None:
        self._board = board
        self._i = i

    def on_tick(self, tick: Any) -> None:
        if tick.est is not None:
            self._board.update(self._i, tick.t, tick.est.p)


__all__ = ["ABOVE_MARGIN", "NONE_ABOVE", "NeighbourBoard", "NeighbourFeed"]
