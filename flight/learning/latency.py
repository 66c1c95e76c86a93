"""Which delay a trained model is applied with in a lockstep flight (config ``online.latency``).

A model trained on a window that ended at flight time ``t_send`` may fly from ``t_send + latency``:

- ``wall``: the trainer's real round trip; the simulation is paced by the wall clock while the
  trainer works. Realistic, but a loaded machine trains slower and so changes the result.
- ``cpu``: the round's CPU time in the trainer (what the round costs, not what the machine was
  doing meanwhile), rounded up to ``quantum_s`` so small run-to-run jitter does not move the swap.
- ``fixed``: ``fixed_s`` for every round: the same flight on any machine, given the trainer's outputs.

In ``cpu`` and ``fixed`` the flight is not paced by the wall: the learner waits for the result
only when flight time reaches the earliest moment it could apply (see ``OnlineLearner``).
On a wall clock (hardware, ``--realtime``) the latency is the wall's whatever this says.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

LatencyMode = Literal["cpu", "fixed", "wall"]
LATENCY_MODES: tuple[str, ...] = ("cpu", "fixed", "wall")


@dataclass(frozen=True)
class LatencyPolicy:
    mode: LatencyMode = "wall"
    fixed_s: float = 0.0  # the delay in ``fixed`` mode
    quantum_s: float = 0.0  # ``cpu`` mode: round the CPU time up to a multiple of this (0: no rounding)

    @property
    def sim_time(self) -> bool:
        """True when the delay is decided from the trainer's report, not the wall clock."""
        return self.mode != "wall"

    @property
    def floor_s(self) -> float:
        """The least delay this policy can give: until then the flight need not wait for the trainer."""
        if self.mode == "fixed":
            return self.fixed_s
        if self.mode == "cpu":
            return self.quantum_s
        return 0.0

    def describe(self) -> str:
        if self.mode == "fixed":
            return f"fixed {self.fixed_s:g} s"
        if self.mode == "cpu":
            return "trainer CPU time" + (f", rounded up to {self.quantum_s:g} s" if self.quantum_s > 0 else "")
        return "wall time (paced)"


def applied_latency(policy: LatencyPolicy, cpu_s: float, wall_s: float) -> float:
    """The delay from send to swap for a round whose trainer reported ``cpu_s`` (and took ``wall_s`` round trip)."""
    if policy.mode == "fixed":
        return policy.fixed_s
    if policy.mode == "wall":
        return wall_s
    if not math.isfinite(cpu_s) or cpu_s < 0.0:
        return wall_s  # no usable CPU report (never seen from a live trainer): the honest fallback
    return quantise_up(cpu_s, policy.quantum_s)


def quantise_up(x: float, quantum: float) -> float:
    """``x`` rounded up to a multiple of ``quantum`` (unchanged when ``quantum`` is 0); at least one quantum."""
    if quantum <= 0.0:
        return x
    # The 1e-9 keeps an exact multiple (e.g. a fixed-point CPU clock) from spilling into the next step.
    return max(1, math.ceil(x / quantum - 1e-9)) * quantum


__all__ = ["LATENCY_MODES", "LatencyMode", "LatencyPolicy", "applied_latency", "quantise_up"]
