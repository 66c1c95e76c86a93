"""KNODE on the full 13-state rigid body: residual networks in torch, their numpy linearisation.

x = (p, v, q, w) in R^13 (scalar-first q), u = (T, Mx, My, Mz); z = (x, u) in R^17.
The hybrid model is x' = f_nom(x, u) + E sum_k w_k f_k(z), w_k = e^(k - n) (newest 1), where
each f_k is one tanh MLP that sees the columns ``inputs`` of z (standardised by fixed
physical scales) and writes the derivative rows ``rows`` (scaled back by ``output_scale``).
Two layouts are used by the paper benchmark:

- ``ResidualLayout.paper()``: the authors' 17 -> 64 -> 13 on all 13 derivatives with raw
  inputs (absolute position included), as in their code (docs/paper-code.md#knode);
- ``ResidualLayout.default()``: cfknode's (v, q, w, u) -> 64 -> (v', w'), normalised,
  translation invariant, never touching the exact kinematic rows p' = v and q'.

Torch is used for training only (the trainer, the bench's worker processes); the MPC side
reads ``QueueWeights`` (plain numpy, picklable) through ``NumpyResidual``.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch
from torch import nn

from cfknode.models.modelfile import queue_weights
from cfknode.kernel.vehicle import VehicleConfig
from cfknode.models.quadrotor import NUMPY, rigid_body_rhs, torch_backend

NX, NU, NZ = 13, 4, 17
_TORCH = torch_backend()


@dataclass(frozen=True)
class ResidualLayout:
    """Which inputs the networks see, which derivative rows they write, and the fixed scalings."""

    inputs: tuple[int, ...]  # columns of z = (x, u)
    rows: tuple[int, ...]  # derivative rows of x'
    hidden: int = 64
    queue_size: int = 3
    input_mean: tuple[float, ...] = ()  # () = zeros
    input_scale: tuple[float, ...] = ()  # () = ones
    output_scale: tuple[float, ...] = ()  # () = ones
    zero_output_init: bool = False  # fresh networks start as "no residual" (else Xavier, the paper's)

    def __post_init__(self) -> None:
        for name, n in (("input_mean", len(self.inputs)), ("input_scale", len(self.inputs)), ("output_scale", len(self.rows))):
            if getattr(self, name) and len(getattr(self, name)) != n:
                raise ValueError(f"{name} needs {n} values, got {len(getattr(self, name))}")
        if any(not 0 <= i < NZ for i in self.inputs) or any(not 0 <= r < NX for r in self.rows):
            raise ValueError("inputs index z (0..16) and rows index x' (0..12)")

    @property
    def mean(self) -> np.ndarray:
        return np.asarray(self.input_mean or (0.0,) * len(self.inputs), dtype=float)

    @property
    def scale(self) -> np.ndarray:
        return np.asarray(self.input_scale or (1.0,) * len(self.inputs), dtype=float)

    @property
    def out_scale(self) -> np.ndarray:
        return np.asarray(self.output_scale or (1.0,) * len(self.rows), dtype=float)

    @classmethod
    def paper(cls) -> ResidualLayout:
        """The authors' network: all 17 raw inputs, all 13 derivative rows."""
        return cls(inputs=tuple(range(NZ)), rows=tuple(range(NX)))

    @classmethod
    def default(cls, hover_thrust: float = 0.2943) -> ResidualLayout:
        """cfknode's: (v, q, w, T, M) -> (v', w'), scaled so every input and output is O(1)."""
        return cls(
            inputs=tuple(range(3, NZ)),
            rows=(3, 4, 5, 10, 11, 12),
            input_mean=(0.0,) * 3 + (1.0, 0.0, 0.0, 0.0) + (0.0,) * 3 + (hover_thrust, 0.0, 0.0, 0.0),
            # The range the MPC may explore, not the (much narrower) spread of one window: a tiny
            # scale turns an untrained direction into a huge spurious slope (1e-4 N m on the
            # moments gave dr/dM 7x the physical 1/J, and IPOPT stalled on it).
            input_scale=(2.0,) * 3 + (0.5,) * 4 + (10.0,) * 3 + (0.2, 5e-3, 5e-3, 1e-3),  # m/s, -, rad/s, N, N m
            output_scale=(5.0,) * 3 + (1.0,) * 3,  # m/s^2, rad/s^2
            # A random Xavier output layer gives a fresh network random slopes the MPC then exploits.
            zero_output_init=True,
        )


@dataclass(frozen=True)
class QueueWeights:
    """A queue as plain numpy: per network (W1 (h, n_in), b1, W2 (n_rows, h), b2), oldest first."""

    layout: ResidualLayout
    networks: tuple[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], ...] = ()

    def __len__(self) -> int:
        return len(self.networks)


class NumpyResidual:
    """The queue's residual and Jacobian in numpy (``cfknode.app.bench.paper.mpc_full.ResidualModel``).

    Normalisation, output scale and forgetting weights are folded into the layers, and the
    networks are stacked along the hidden axis: one MLP with p x h hidden units.
    """

    def __init__(self, weights: QueueWeights) -> None:
        lay = weights.layout
        self.rows = lay.rows
        self._inputs = np.asarray(lay.inputs)
        self.n_networks = len(weights)
        if not weights.networks:
            raise ValueError("an empty queue has no residual: pass None to the MPC instead")
        wq = queue_weights(len(weights))
        w1s, b1s, w2s, b2 = [], [], [], np.zeros(len(lay.rows))
        for j, (w1, b1, w2, b2j) in enumerate(weights.networks):
            w1n = w1 / lay.scale[None, :]
            w1s.append(w1n)
            b1s.append(b1 - w1n @ lay.mean)
            gain = wq[j] * lay.out_scale
            w2s.append(gain[:, None] * w2)
            b2 = b2 + gain * b2j
        self._w1 = np.ascontiguousarray(np.concatenate(w1s, axis=0))  # (H, n_in)
        self._w1t = np.ascontiguousarray(self._w1.T)
        self._b1 = np.concatenate(b1s)
        self._w2 = np.ascontiguousarray(np.concatenate(w2s, axis=1))  # (n_rows, H)
        self._w2t = np.ascontiguousarray(self._w2.T)
        self._b2 = b2

    def value(self, z: np.ndarray) -> np.ndarray:
        """Residual (n, n_rows) on the rows, for z (n, 17)."""
        h = np.tanh(z[:, self._inputs] @ self._w1t + self._b1)
        return h @ self._w2t + self._b2

    def value_and_jacobian(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h = np.tanh(z[:, self._inputs] @ self._w1t + self._b1)
        r = h @ self._w2t + self._b2
        g = self._w2[None, :, :] * (1.0 - h * h)[:, None, :]  # (n, rows, H)
        jz = np.zeros((z.shape[0], len(self.rows), NZ))
        jz[:, :, self._inputs] = g @ self._w1
        return r, jz


# --- torch ------------------------------------------------------------------------------


class RigidBodyNet(nn.Module):
    """One residual MLP on z = (x, u); fresh ones get Xavier-uniform weights and zero biases."""

    def __init__(self, layout: ResidualLayout, dtype: torch.dtype, generator: torch.Generator) -> None:
        super().__init__()
        self.register_buffer("inputs", torch.as_tensor(layout.inputs, dtype=torch.long))
        self.l1 = nn.Linear(len(layout.inputs), layout.hidden, dtype=dtype)
        self.l2 = nn.Linear(layout.hidden, len(layout.rows), dtype=dtype)
        with torch.no_grad():
            for layer in (self.l1, self.l2):
                nn.init.xavier_uniform_(layer.weight, generator=generator)
                layer.bias.zero_()
            if layout.zero_output_init:
                self.l2.weight.zero_()
        self.register_buffer("mean", torch.as_tensor(layout.mean, dtype=dtype))
        self.register_buffer("scale", torch.as_tensor(layout.scale, dtype=dtype))
        self.register_buffer("out_scale", torch.as_tensor(layout.out_scale, dtype=dtype))
        # The paper's raw 17 -> 13 network needs no gather and no scaling: skip those ops (hot loop).
        self.raw_inputs = layout.inputs == tuple(range(NZ)) and not layout.input_mean and not layout.input_scale
        self.raw_outputs = not layout.output_scale

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        zin = z if self.raw_inputs else (z[..., self.inputs] - self.mean) / self.scale
        out = self.l2(torch.tanh(self.l1(zin)))
        return out if self.raw_outputs else out * self.out_scale


class RigidBodyQueue(nn.Module):
    """Up to ``layout.queue_size`` networks, oldest first; only the newest is trainable."""

    def __init__(self, layout: ResidualLayout, dtype: torch.dtype = torch.float32, seed: int = 0) -> None:
        super().__init__()
        self.layout = layout
        self.dtype = dtype
        self.networks = nn.ModuleList()
        self._rows = list(layout.rows)
        self._all_rows = layout.rows == tuple(range(NX))
        self._row_index = torch.as_tensor(layout.rows, dtype=torch.long)
        # A private generator: reproducible initialisation without touching torch's global RNG.
        self._generator = torch.Generator().manual_seed(seed)

    def __len__(self) -> int:
        return len(self.networks)

    def push(self, copy_from_newest: bool = False) -> RigidBodyNet:
        """Append a network (fresh, or a copy of the newest), drop the oldest beyond the queue size."""
        if copy_from_newest and self.networks:
            net = copy.deepcopy(self.networks[-1])
        else:
            net = RigidBodyNet(self.layout, self.dtype, self._generator)
        self.networks.append(net)
        if len(self.networks) > self.layout.queue_size:
            del self.networks[0]
        for k, n in enumerate(self.networks):
            n.requires_grad_(k == len(self.networks) - 1)
        return net

    def residual(self, z: torch.Tensor) -> torch.Tensor:
        w = queue_weights(len(self.networks))
        out = float(w[-1]) * self.networks[-1](z)
        for k in range(len(self.networks) - 1):
            out = out + float(w[k]) * self.networks[k](z)
        return out

    def rhs(self, x: torch.Tensor, u: torch.Tensor, mass: float, inertia: Sequence[float], gravity: float) -> torch.Tensor:
        f = rigid_body_rhs(x, u, mass, inertia, gravity, _TORCH)
        if not self.networks:
            return f
        r = self.residual(torch.cat((x, u), dim=-1))
        if self._all_rows:
            return f + r
        return f.index_add(-1, self._row_index, r)

    def to_weights(self) -> QueueWeights:
        nets = tuple(
            tuple(t.detach().to(torch.float64).numpy().copy() for t in (n.l1.weight, n.l1.bias, n.l2.weight, n.l2.bias))
            for n in self.networks
        )
        return QueueWeights(self.layout, nets)

    @classmethod
    def from_weights(cls, weights: QueueWeights, dtype: torch.dtype = torch.float32, seed: int = 0) -> RigidBodyQueue:
        queue = cls(weights.layout, dtype, seed)
        for w1, b1, w2, b2 in weights.networks:
            net = queue.push()
            with torch.no_grad():
                for t, a in ((net.l1.weight, w1), (net.l1.bias, b1), (net.l2.weight, w2), (net.l2.bias, b2)):
                    t.copy_(torch.tensor(a, dtype=dtype))  # a copy: weights from Ray's store are read-only
        return queue


# --- data and training --------------------------------------------------------------------------


@dataclass(frozen=True)
class OneStepPairs:
    """Samples z0 = (x_i, u_i) -> x_{i+1} one plant step h later."""

    z0: np.ndarray  # (m, 17)
    x1: np.ndarray  # (m, 13)

    def __len__(self) -> int:
        return int(self.z0.shape[0])

    @classmethod
    def aligned(cls, states: np.ndarray, inputs: np.ndarray) -> OneStepPairs:
        """states (m+1, 13) and inputs (m, 4), input i held from state i to state i+1."""
        return cls(np.concatenate((states[:-1], inputs), axis=1), states[1:].copy())

    @classmethod
    def from_paper_rows(cls, rows: np.ndarray) -> OneStepPairs:
        """The original's pairing of its data rows [x_{k+1}, u_k]: row j's input is used to go
        from row j's state to row j+1's, although u_{k+1} drove that step (wrong at every
        control switch, 1 pair in 25)."""
        return cls(rows[:-1].copy(), rows[1:, :NX].copy())

    @staticmethod
    def concat(parts: Sequence[OneStepPairs]) -> OneStepPairs:
        return OneStepPairs(np.concatenate([p.z0 for p in parts]), np.concatenate([p.x1 for p in parts]))

    def split(self, fraction: float) -> tuple[OneStepPairs, OneStepPairs]:
        """(first 1 - fraction, last fraction) in time order."""
        n_val = int(round(fraction * len(self)))
        cut = len(self) - n_val
        return OneStepPairs(self.z0[:cut], self.x1[:cut]), OneStepPairs(self.z0[cut:], self.x1[cut:])


@dataclass(frozen=True)
class TrainSettings:
    """One training round of the newest network (full-batch Adam, the other networks frozen).

    ``loss``:
    - "paper", the original's: one RK4 step of h through the hybrid model, the MSE over the 13
      states against the next sample, averaged with the trivial initial point (which halves
      it), plus ``l2`` times the squared norm of *all* networks' parameters;
    - "residual", cfknode's: the network regresses the apparent residual
      y = (x1 - x0 - nominal RK4 increment) / h on its rows, scaled by the output scales,
      plus ``l2`` on the trained network only.  Over a 2 ms step the residual is constant to
      first order, so this is the one-step loss without integrating the networks: about 10x
      cheaper per epoch, which is training latency saved.
    """

    epochs: int = 80
    lr: float = 0.01
    l2: float = 5e-8
    loss: str = "paper"
    h: float = 0.002  # plant step of the pairs

    def __post_init__(self) -> None:
        if self.loss not in ("paper", "residual"):
            raise ValueError(f"unknown loss {self.loss!r}; expected 'paper' or 'residual'")


@dataclass(frozen=True)
class TrainStats:
    loss_first: float
    loss_last: float
    epochs: int
    wall_time: float  # s
    history: tuple[float, ...] = field(default_factory=tuple, repr=False)


def _rk4_delta(queue: RigidBodyQueue, x: torch.Tensor, u: torch.Tensor, h: float, phys: VehicleConfig) -> torch.Tensor:
    def f(y: torch.Tensor) -> torch.Tensor:
        return queue.rhs(y, u, phys.mass, phys.inertia, phys.gravity)

    k1 = f(x)
    k2 = f(x + 0.5 * h * k1)
    k3 = f(x + 0.5 * h * k2)
    k4 = f(x + h * k3)
    return (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def nominal_increment(pairs: OneStepPairs, h: float, phys: VehicleConfig) -> np.ndarray:
    """x1 - x0 predicted by one RK4 step of the nominal model (numpy, float64): (m, 13)."""
    x0, u = pairs.z0[:, :NX], pairs.z0[:, NX:]

    def f(y: np.ndarray) -> np.ndarray:
        return rigid_body_rhs(y, u, phys.mass, phys.inertia, phys.gravity, NUMPY)

    k1 = f(x0)
    k2 = f(x0 + 0.5 * h * k1)
    k3 = f(x0 + 0.5 * h * k2)
    k4 = f(x0 + h * k3)
    return (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def apparent_residual(pairs: OneStepPairs, rows: Sequence[int], h: float, phys: VehicleConfig) -> np.ndarray:
    """(x1 - x0 - nominal increment) / h on ``rows``: what the residual must have been, (m, len(rows))."""
    return (pairs.x1 - pairs.z0[:, :NX] - nominal_increment(pairs, h, phys))[:, list(rows)] / h


def _paper_loss(queue: RigidBodyQueue, pred: torch.Tensor, delta: torch.Tensor, l2: float) -> torch.Tensor:
    reg = sum((p * p).sum() for p in queue.parameters())
    return 0.5 * torch.mean((pred - delta) ** 2) + l2 * reg


def train_newest(queue: RigidBodyQueue, pairs: OneStepPairs, settings: TrainSettings, phys: VehicleConfig) -> TrainStats:
    """Train the newest network of ``queue`` in place with full-batch Adam (the others frozen)."""
    if not queue.networks:
        raise ValueError("push() a network before training")
    # Two threads on a shared 2-core machine slowed small batches 4-80x
    # (docs/solver-timings.md#training).
    torch.set_num_threads(1)
    start = time.perf_counter()
    newest = queue.networks[-1]
    opt = torch.optim.Adam(list(newest.parameters()), lr=settings.lr)
    dtype = queue.dtype
    if settings.loss == "paper":
        x0 = torch.as_tensor(pairs.z0[:, :NX], dtype=dtype)
        u = torch.as_tensor(pairs.z0[:, NX:], dtype=dtype)
        # The target increment is formed in float64, so float32 training does not lose it to rounding.
        delta = torch.as_tensor(pairs.x1 - pairs.z0[:, :NX], dtype=dtype)

        def objective() -> torch.Tensor:
            return _paper_loss(queue, _rk4_delta(queue, x0, u, settings.h, phys), delta, settings.l2)

    else:
        z = torch.as_tensor(pairs.z0, dtype=dtype)
        scale = torch.as_tensor(queue.layout.out_scale, dtype=dtype)
        with torch.no_grad():
            frozen = queue.residual(z) - newest(z)  # the newest has weight 1
        target = (torch.as_tensor(apparent_residual(pairs, queue.layout.rows, settings.h, phys), dtype=dtype) - frozen) / scale

        def objective() -> torch.Tensor:
            err = newest(z) / scale - target
            return torch.mean((err * err).sum(dim=1)) + settings.l2 * sum((p * p).sum() for p in newest.parameters())

    history = []
    for _ in range(settings.epochs):
        opt.zero_grad(set_to_none=True)
        loss = objective()
        loss.backward()
        opt.step()
        history.append(float(loss.detach()))
    with torch.no_grad():
        final = float(objective())
    return TrainStats(history[0] if history else final, final, settings.epochs, time.perf_counter() - start, tuple(history))


def fit_output_layer(queue: RigidBodyQueue, pairs: OneStepPairs, h: float, phys: VehicleConfig, ridge: float) -> None:
    """Re-fit the newest network's output layer in closed form (ridge toward its current value).

    The "residual" loss is linear in the output layer: one small solve reaches its minimum,
    where Adam would need many steps for a jump in the residual (a mass change).
    """
    if len(pairs) == 0:
        return
    newest = queue.networks[-1]
    with torch.no_grad():
        z = torch.as_tensor(pairs.z0, dtype=queue.dtype)
        frozen = (queue.residual(z) - newest(z)).to(torch.float64).numpy()  # weight of the newest is 1
        zin = z if newest.raw_inputs else (z[:, newest.inputs] - newest.mean) / newest.scale
        feats = torch.tanh(newest.l1(zin)).to(torch.float64).numpy()
        w2 = newest.l2.weight.detach().to(torch.float64).numpy()
        b2 = newest.l2.bias.detach().to(torch.float64).numpy()
    y = (apparent_residual(pairs, queue.layout.rows, h, phys) - frozen) / queue.layout.out_scale[None, :]
    a = np.concatenate((feats, np.ones((feats.shape[0], 1))), axis=1)
    prior = np.concatenate((w2, b2[:, None]), axis=1)  # (rows, H + 1)
    lhs = a.T @ a + ridge * np.eye(a.shape[1])
    theta = np.linalg.solve(lhs, a.T @ y + ridge * prior.T).T
    with torch.no_grad():
        newest.l2.weight.copy_(torch.as_tensor(theta[:, :-1], dtype=queue.dtype))
        newest.l2.bias.copy_(torch.as_tensor(theta[:, -1], dtype=queue.dtype))


def residual_error(queue: RigidBodyQueue, pairs: OneStepPairs, h: float, phys: VehicleConfig) -> float:
    """Mean squared error of the queue's residual against the apparent residual, on its rows and
    divided by its output scales (an empty queue scores the nominal model): the validation metric."""
    if len(pairs) == 0:
        return float("nan")
    y = apparent_residual(pairs, queue.layout.rows, h, phys)
    if queue.networks:
        with torch.no_grad():
            y = y - queue.residual(torch.as_tensor(pairs.z0, dtype=queue.dtype)).to(torch.float64).numpy()
    err = y / queue.layout.out_scale[None, :]
    return float(np.mean(np.sum(err * err, axis=1)))


__all__ = [
    "NumpyResidual",
    "OneStepPairs",
    "QueueWeights",
    "ResidualLayout",
    "RigidBodyNet",
    "RigidBodyQueue",
    "TrainSettings",
    "TrainStats",
    "apparent_residual",
    "fit_output_layer",
    "nominal_increment",
    "residual_error",
    "train_newest",
]
