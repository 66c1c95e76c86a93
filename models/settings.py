"""Settings of the models package: the residual networks and their training."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal



@dataclass(frozen=True)
class KnodeConfig:
    hidden: tuple[int, ...]
    activation: Literal["tanh", "softplus", "relu"]
    queue_size: int
    max_residual: float


@dataclass(frozen=True)
class TrainingConfig:
    epochs: int
    lr: float
    weight_decay: float
    method: Literal["rk4", "euler", "dopri5"]
    adjoint: bool
    seed: int
    velocity_filter_hz: float
    validation_fraction: float
    batch_size: int = 16384  # pairs per Adam step; a larger dataset trains on a random batch each step


@dataclass(frozen=True)
class FaultInjection:
    """Test hooks for online learning: the trainer fails at this round (0 = never)."""

    crash_at_round: int
    hang_at_round: int
    nan_at_round: int
