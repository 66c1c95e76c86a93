"""The KNODE residual the MPC predicts with, linearised once per tick (lin-RTI).

The networks stay out of the CasADi graph (docs/solver-timings.md#networks-outside-casadi): each tick the queue is
evaluated with its Jacobians in batched numpy at the previous solution's nodes, and the
affine result becomes the MPC's per-stage parameters. Swapping a model is one reference
assignment between ticks, so it never rebuilds or recompiles the solver.

The nodes are the last plan's, known before the next pose arrives: the linearisation can be done after a send,
as the real-time iteration's preparation phase (``ModelSlot.prepare``), and the next tick only checks that the
model it was done for still flies.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from cfknode.flight.mpc import ResidualLinearisation


class Linearisable(Protocol):
    def linearise(self, x_nodes: np.ndarray, u_nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    def evaluate(self, x: np.ndarray, u: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class PreparedResidual:
    """A linearisation done ahead of its tick: valid while ``model`` (at ``version``) flies."""

    model: Any
    version: int
    residual: ResidualLinearisation


@dataclass(frozen=True)
class SwapRecord:
    version: int
    t: float  # flight time of the swap
    swap_s: float  # wall time the swap took


class ModelSlot:
    """Holds the residual model in use; ``residual`` is called every tick, ``swap`` between ticks."""

    def __init__(self, model: Linearisable | None, version: int = 0) -> None:
        self._model = model
        self.version = version
        self.swaps: list[SwapRecord] = []
        # A fleet drone's neighbour input (flight/neighbours.py ``NeighbourFeed``; docs/fleet.md#neighbour-input):
        # a model that takes it is linearised at the neighbour's positions over the horizon. None: none.
        self.neighbour: Any = None
        # Where the drone above was at the last linearisation's first node, or at the measured state's time once
        # the layer was told the model there (``residual_at``; None: not given to the model): the
        # fast layer re-bases a swap at the positions the flying model saw (flight/adaptation/recent.py).
        self.last_neighbour: np.ndarray | None = None
        # s the plan's horizontal nodes lead the thrust's (estimator.command_delay less command_delay_z): a
        # wake-only model's vertical force acts with the thrust, so it is taken where the drone is then.
        self.vertical_lead = 0.0

    @property
    def model(self) -> Linearisable | None:
        return self._model

    def residual(self, x_nodes: np.ndarray, u_nodes: np.ndarray) -> ResidualLinearisation | None:
        """The affine residual at the given nodes (N, 6) and (N, 3); None when flying nominal."""
        return self._linearise(x_nodes, u_nodes, measured=False)

    def residual_at(self, x: np.ndarray, u: np.ndarray) -> ResidualLinearisation | None:
        """``residual`` at the measured state x (6,), u (3,) when the plan starts ahead of it (the command delay):
        one stage, exact there, with the drone above where it is now (``last_neighbour`` too)."""
        return self._linearise(np.asarray(x, dtype=float)[None], np.asarray(u, dtype=float)[None], measured=True)

    def _linearise(self, x_nodes: np.ndarray, u_nodes: np.ndarray, measured: bool) -> ResidualLinearisation | None:
        self.last_neighbour = None
        if self._model is None or not getattr(self._model, "takes_neighbour", False):
            # Where the drone above is, though nothing flown sees it: a first swap to a model that does is re-based
            # there (evaluated at its stand-in, a wake model put its peak into the layer's constant).
            if self.neighbour is not None:
                p = x_nodes[0, 0:3]
                self.last_neighbour = p + self.neighbour.relative(p)
            if self._model is None:
                return None
        nb = None
        if self.neighbour is not None and getattr(self._model, "takes_neighbour", False):
            if self.vertical_lead > 0.0 and not measured and getattr(self._model, "wake_only", False):
                # A jet 6 cm wide, crossed at 0.5 m/s in 0.12 s: taken 65 ms early it is half a crossing off.
                x_nodes = x_nodes.copy()
                x_nodes[:, 0:3] -= x_nodes[:, 3:6] * self.vertical_lead
                measured = True
            nb = self.neighbour.horizon(x_nodes, measured)
            self.last_neighbour = None if nb is None else nb[0]
        c, jx, ju = self._model.linearise(x_nodes, u_nodes) if nb is None else \
            self._model.linearise(x_nodes, u_nodes, nb)  # type: ignore[call-arg]
        return ResidualLinearisation(c, jx, ju)

    def prepare(self, x_nodes: np.ndarray, u_nodes: np.ndarray) -> PreparedResidual | None:
        """``residual`` at the next tick's nodes, done now; None where it cannot be done ahead: flying nominal,
        or a model that takes the neighbour's position, which moves until the tick."""
        model = self._model
        if model is None or (self.neighbour is not None and getattr(model, "takes_neighbour", False)):
            return None
        residual = self.residual(x_nodes, u_nodes)
        return None if residual is None else PreparedResidual(model, self.version, residual)

    def holds(self, prepared: PreparedResidual) -> bool:
        """Whether ``prepared`` was done for the model flying now (no swap since): then it is this tick's residual."""
        return prepared.model is self._model and prepared.version == self.version

    def swap(self, model: Linearisable | None, version: int, now: float) -> SwapRecord:
        start = time.perf_counter()
        self._model = model
        self.version = version
        record = SwapRecord(version=version, t=now, swap_s=time.perf_counter() - start)
        self.swaps.append(record)
        return record


def plan_nodes(x_pred: np.ndarray | None, u_pred: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
    """The previous solution's nodes (RTI), or None without a usable one (the first tick, a failed solve)."""
    if x_pred is not None and u_pred is not None and np.all(np.isfinite(x_pred)) and np.all(np.isfinite(u_pred)):
        return x_pred[:-1], u_pred
    return None


def linearisation_points(
    x0: np.ndarray, ref_a: np.ndarray, x_pred: np.ndarray | None, u_pred: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """Nodes to linearise at: the previous solution (RTI), or the current state and the
    reference acceleration on the first tick and after a failed solve."""
    nodes = plan_nodes(x_pred, u_pred)
    if nodes is not None:
        return nodes
    n = ref_a.shape[0] - 1
    return np.broadcast_to(x0, (n, x0.shape[0])), ref_a[:-1]
