"""Settings of the models package: the residual networks and their training."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from cfknode.kernel.setting import setting


@dataclass(frozen=True)
class KnodeConfig:
    hidden: tuple[int, ...] = setting(unit="units", low=1, high=1024, doc="hidden layer widths of each residual MLP")
    activation: Literal["tanh", "softplus", "relu"] = setting(doc="tanh | softplus | relu")
    queue_size: int = setting(low=1, high=10, doc="p: networks kept, weights e^(k-p), oldest e^-(p-1) ... newest 1")
    max_residual: float = setting(unit="m/s^2", low=0, high=100, open_low=True,
        doc="larger residuals are rejected as not physical")


@dataclass(frozen=True)
class TrainingConfig:
    epochs: int = setting(low=1, high=100000, doc="Adam steps (full batch up to batch_size pairs)")
    lr: float = setting(low=0, high=1, open_low=True, doc="Adam learning rate")
    weight_decay: float = setting(low=0, high=100,
        doc="L2 on the trainable net; the loss is in (m/s^2)^2 (1e-6 fit as well but extrapolated worse)")
    method: Literal["rk4", "euler", "dopri5"] = setting(
        doc="rk4 | euler (fixed step, one per pair) | dopri5 (adaptive)")
    adjoint: bool = setting(doc="torchdiffeq adjoint; the paper uses it, exact backprop is cheaper for one step")
    seed: int = setting(low=0, high=4294967295, doc="seed of the networks' initial weights and the batch draws")
    velocity_filter_hz: float = setting(unit="Hz", low=0.5, high=100,
        doc="low-pass cut-off applied to velocities before training")
    validation_fraction: float = setting(low=0, high=1, open_low=True, open_high=True,
        doc="the last fraction of each log is held out for the validation error")
    command_lag_s: tuple[float, float] = setting((0.0, 0.0), unit="s", low=0, high=0.5,
        doc="(x/y, z) lags the recorded commands act through: targets use the lagged command (online.layer_command_lag_s)")
    batch_size: int = setting(16384, low=64, high=10000000,
        doc="pairs per step; above it each step draws a random batch (docs/data.md#training-speed)")


@dataclass(frozen=True)
class FaultInjection:
    """Test hooks for online learning: the trainer fails at this round (0 = never)."""

    crash_at_round: int = setting(low=0, high=100000, doc="test hook: the trainer crashes at this round (0 = never)")
    hang_at_round: int = setting(low=0, high=100000, doc="test hook: the trainer hangs at this round (0 = never)")
    nan_at_round: int = setting(low=0, high=100000,
        doc="test hook: the trainer returns NaN weights at this round (0 = never)")
