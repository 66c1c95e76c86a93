"""KNODE in torch: residual networks on v' with forgetting weights, and the hybrid ODE.

x = (p, v) in R^6, u = commanded world acceleration in R^3.  Nominal: p' = v, v' = u
(``cfknode.models.quadrotor.translational_rhs``).  KNODE adds

    r(x, u) = sum_k w_k f_k(v, u),   w_k = e^(k - n), k = 1..n (newest last, weight 1)

to v' only: the kinematic rows p' = v are exact and never learned.  Each network sees the
translation-invariant input (v, u), standardised by its own input mean/scale, and its output
is multiplied by its own output scale (all stored in the model file).  Only the newest
network is trainable; pushing onto a full queue drops the oldest (the paper's Section 3.2).

Torch lives here, in ``training.py`` and in the trainer process only; the flight process
evaluates the same queue with ``residual_np``.
"""

from __future__ import annotations

import copy
from typing import Any, Iterator, Mapping, Sequence

import numpy as np
import torch
from torch import nn

from cfknode.models.settings import KnodeConfig
from cfknode.models.modelfile import (
    ACTIVATIONS,
    INPUT_NAMES,
    N_IN,
    N_OUT,
    NEIGHBOUR_INPUT_NAMES,
    ModelFile,
    NetworkWeights,
    Normalisation,
    TrainingInfo,
    queue_weights,
)
from cfknode.models.quadrotor import torch_backend, translational_rhs


class ResidualNet(nn.Module):
    """One residual MLP: (v, u) raw -> residual acceleration on v' (m/s^2)."""

    def __init__(
        self,
        hidden: Sequence[int],
        activation: str,
        normalisation: Normalisation,
        dtype: torch.dtype = torch.float64,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        if activation not in ACTIVATIONS:
            raise ValueError(f"unknown activation {activation!r}; expected one of {ACTIVATIONS}")
        self.activation = activation
        # (v, u), or (v, u, neighbour's relative position): the normalisation's width says which.
        sizes = [len(normalisation.input_mean), *hidden, N_OUT]
        self.layers = nn.ModuleList(nn.Linear(a, b, dtype=dtype) for a, b in zip(sizes[:-1], sizes[1:]))
        gain = nn.init.calculate_gain("tanh") if activation == "tanh" else 1.0
        with torch.no_grad():
            for layer in self.layers[:-1]:
                nn.init.xavier_uniform_(layer.weight, gain=gain, generator=generator)
                layer.bias.zero_()
            # A zero output layer makes a fresh network "no residual": adding it never changes the model.
            self.layers[-1].weight.zero_()
            self.layers[-1].bias.zero_()
        self.register_buffer("input_mean", torch.as_tensor(normalisation.input_mean, dtype=dtype).clone())
        self.register_buffer("input_scale", torch.as_tensor(normalisation.input_scale, dtype=dtype).clone())
        self.register_buffer("output_scale", torch.as_tensor(normalisation.output_scale, dtype=dtype).clone())

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        h = (z - self.input_mean) / self.input_scale
        for layer in self.layers[:-1]:
            h = _activate(layer(h), self.activation)
        return self.layers[-1](h) * self.output_scale

    @property
    def normalisation(self) -> Normalisation:
        return Normalisation(
            self.input_mean.detach().cpu().numpy().copy(),
            self.input_scale.detach().cpu().numpy().copy(),
            self.output_scale.detach().cpu().numpy().copy(),
        )


class KnodeQueue(nn.Module):
    """Up to ``queue_size`` residual networks, oldest first; only the newest is trainable."""

    def __init__(
        self,
        hidden: Sequence[int],
        activation: str,
        queue_size: int,
        normalisation: Normalisation | None = None,
        dtype: torch.dtype = torch.float64,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        if activation not in ACTIVATIONS:
            raise ValueError(f"unknown activation {activation!r}; expected one of {ACTIVATIONS}")
        self.hidden = tuple(int(h) for h in hidden)
        self.activation = activation
        self.queue_size = queue_size
        self.dtype = dtype
        self.default_normalisation = normalisation or Normalisation.identity()
        self.networks = nn.ModuleList()
        # The queue's own generator keeps network initialisation reproducible without touching torch's global RNG.
        self._generator = torch.Generator().manual_seed(seed)

    @classmethod
    def from_config(cls, knode_cfg: KnodeConfig, normalisation: Normalisation | None = None, seed: int = 0) -> KnodeQueue:
        """From the ``knode`` config section (hidden, activation, queue_size)."""
        return cls(knode_cfg.hidden, knode_cfg.activation, knode_cfg.queue_size, normalisation, seed=seed)

    def __len__(self) -> int:
        return len(self.networks)

    @property
    def newest(self) -> ResidualNet:
        if not self.networks:
            raise IndexError("the queue is empty")
        return self.networks[-1]

    def push(self, copy_from_newest: bool = False, normalisation: Normalisation | None = None) -> ResidualNet:
        """Append a network (dropping the oldest when full), freeze the others, and return it.

        ``copy_from_newest`` warm-starts it from the current newest (weights and normalisation);
        otherwise it is fresh (zero output layer) with ``normalisation`` or the queue default.
        """
        if copy_from_newest and self.networks:
            if normalisation is not None:
                raise ValueError("a warm-started network keeps its predecessor's normalisation")
            net = copy.deepcopy(self.newest)
        else:
            net = ResidualNet(
                self.hidden,
                self.activation,
                normalisation or self.default_normalisation,
                dtype=self.dtype,
                generator=self._generator,
            )
        self.append_network(net)
        return net

    def append_network(self, net: ResidualNet) -> None:
        """Append an existing network (e.g. loaded from a file) with the queue's push semantics."""
        if len(self.networks) == self.queue_size:
            del self.networks[0]
        self.networks.append(net)
        self._set_trainable()

    def _set_trainable(self) -> None:
        last = len(self.networks) - 1
        for k, net in enumerate(self.networks):
            for param in net.parameters():
                param.requires_grad_(k == last)

    def weights(self) -> torch.Tensor:
        """Forgetting weights w_k = e^(k - n), oldest first, newest 1."""
        return torch.as_tensor(queue_weights(len(self.networks)), dtype=self.dtype)

    def trainable_parameters(self) -> Iterator[nn.Parameter]:
        return (p for p in self.parameters() if p.requires_grad)

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Residual on v', shape (..., 3), for x (..., 6) and u (..., 3), or u (..., 6) = (command,
        neighbour's relative position) for networks with the neighbour input."""
        z = torch.cat((x[..., 3:6], u), dim=-1)
        if not self.networks:
            return torch.zeros(z.shape[:-1] + (N_OUT,), dtype=z.dtype)
        w = queue_weights(len(self.networks))
        out = float(w[-1]) * self.networks[-1](z)
        for k in range(len(self.networks) - 1):
            out = out + float(w[k]) * self.networks[k](z)
        return out

    def rhs(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """Hybrid derivative: nominal (p' = v, v' = u) plus the residual on the v' rows only."""
        nominal = translational_rhs(x, u[..., 0:3], _TORCH)  # the neighbour columns are the network's only
        residual = self(x, u)
        return torch.cat((nominal[..., 0:3], nominal[..., 3:6] + residual), dim=-1)


class TrainingResidual(nn.Module):
    """The queue's residual for one training run: newest network + the frozen ones folded.

    The frozen networks cannot change while the newest trains, so they are snapshotted into
    one stacked MLP (the same folding as ``residual_np``): one batched product per layer
    instead of p - 1 separate networks, about 0.5 ms less per epoch and frozen network.
    Build it after the last push and do not keep it across pushes.
    """

    def __init__(self, queue: KnodeQueue) -> None:
        super().__init__()
        if not queue.networks:
            raise ValueError("the queue is empty")
        self.newest = queue.newest
        self.activation = queue.activation
        frozen = list(queue.networks)[:-1]
        self.n_frozen = len(frozen)
        if frozen:
            from cfknode.models.residual_np import ResidualQueue

            sub = from_torch_queue(_subqueue(queue, frozen))
            stacked = ResidualQueue.from_model_file(sub)
            # In the full queue the frozen ones sit one place further back: weights e^(k-n) = e^-1 e^(k-(n-1)).
            back = float(np.exp(-1.0))
            layers = stacked.layers
            for i, layer in enumerate(layers):
                gain = back if i == len(layers) - 1 else 1.0
                self.register_buffer(f"w{i}", torch.as_tensor(gain * layer.weight_t, dtype=queue.dtype))
                self.register_buffer(f"b{i}", torch.as_tensor(layer.bias, dtype=queue.dtype))
            self.register_buffer("out_bias", torch.as_tensor(back * stacked.output_bias, dtype=queue.dtype))
            self.n_layers = len(layers)

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        z = torch.cat((x[..., 3:6], u), dim=-1)
        out = self.newest(z)
        if self.n_frozen:
            h = z
            for i in range(self.n_layers - 1):
                h = _activate(torch.matmul(h, getattr(self, f"w{i}")) + getattr(self, f"b{i}"), self.activation)
            out = out + torch.matmul(h, getattr(self, f"w{self.n_layers - 1}")).sum(dim=0) + self.out_bias
        return out

    def rhs(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        nominal = translational_rhs(x, u[..., 0:3], _TORCH)
        return torch.cat((nominal[..., 0:3], nominal[..., 3:6] + self(x, u)), dim=-1)


def _subqueue(queue: KnodeQueue, networks: list[ResidualNet]) -> KnodeQueue:
    sub = KnodeQueue(queue.hidden, queue.activation, max(1, len(networks)), dtype=queue.dtype)
    for net in networks:
        sub.networks.append(net)  # shares the modules; only read for the snapshot
    return sub


def _activate(a: torch.Tensor, kind: str) -> torch.Tensor:
    if kind == "tanh":
        return torch.tanh(a)
    if kind == "softplus":
        # logaddexp (not F.softplus, which turns linear above 20) so numpy renders the same function.
        return torch.logaddexp(a, torch.zeros((), dtype=a.dtype))
    return torch.relu(a)


_TORCH = torch_backend()


def to_torch_queue(mf: ModelFile, dtype: torch.dtype = torch.float64, seed: int = 0) -> KnodeQueue:
    """A ``KnodeQueue`` holding the file's networks (oldest first; the newest trainable)."""
    default = mf.networks[-1].normalisation if mf.networks else None
    queue = KnodeQueue(mf.hidden, mf.activation, mf.queue_size, default, dtype=dtype, seed=seed)
    for weights in mf.networks:
        # A private generator: the random init is overwritten at once, so leave torch's global RNG alone.
        net = ResidualNet(mf.hidden, mf.activation, weights.normalisation, dtype=dtype, generator=torch.Generator())
        with torch.no_grad():
            for layer, (w, b) in zip(net.layers, weights.layers):
                layer.weight.copy_(torch.as_tensor(w, dtype=dtype))
                layer.bias.copy_(torch.as_tensor(b, dtype=dtype))
        queue.append_network(net)
    return queue


def from_torch_queue(
    queue: KnodeQueue,
    training: TrainingInfo | None = None,
    extra: Mapping[str, Any] | None = None,
) -> ModelFile:
    """The queue's weights as numpy arrays with its architecture, ready for ``save_model``."""
    networks = []
    for net in queue.networks:
        layers = tuple(
            (
                layer.weight.detach().cpu().to(torch.float64).numpy().copy(),
                layer.bias.detach().cpu().to(torch.float64).numpy().copy(),
            )
            for layer in net.layers
        )
        networks.append(NetworkWeights(layers, net.normalisation))
    n_in = len(networks[-1].normalisation.input_mean) if networks else N_IN
    return ModelFile(
        hidden=queue.hidden,
        activation=queue.activation,
        queue_size=queue.queue_size,
        networks=tuple(networks),
        training=training,
        extra=dict(extra or {}),
        inputs=NEIGHBOUR_INPUT_NAMES if n_in > N_IN else INPUT_NAMES,
    )


def residual_numpy(queue: KnodeQueue, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Evaluate the torch queue on numpy arrays (no grad); a convenience for checks and tests."""
    with torch.no_grad():
        out = queue(torch.as_tensor(x, dtype=queue.dtype), torch.as_tensor(u, dtype=queue.dtype))
    return out.cpu().numpy()


__all__ = ["KnodeQueue", "ResidualNet", "TrainingResidual", "from_torch_queue", "residual_numpy", "to_torch_queue"]
