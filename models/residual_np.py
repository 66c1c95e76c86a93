"""The KNODE residual queue in plain numpy: evaluation and batched linearisation for the MPC.

The flight process must not import torch, so it reads a ``ModelFile`` and evaluates the
queue here.  At load time each network's input normalisation is folded into its first
layer (W/s, b - W m/s), and its output scale and forgetting weight w_j into its output
layer; the p networks are then stacked along a leading axis, so every layer is ONE batched
matrix product over all networks and all N nodes, (p, N, h_in) @ (p, h_in, h_out).

(A single block-diagonal matrix would also work, but it multiplies (p-1)/p zeros, and the
larger product crosses OpenBLAS's multithreading threshold, which on a busy 2-core machine
showed 16 ms p99 spikes; p small products stay single-threaded and took half the time.)

The residual acts on v' only and its inputs are z = (v, u): the Jacobian with respect to
position is exactly zero. A queue with the neighbour input (a fleet's ``fleet.neighbour_input``,
docs/fleet.md#neighbour-input) also sees d = p_nb - p, the relative position of the drone above: the
MPC's linearisation takes the neighbour's positions at its nodes (``nb``, known parameters), so its
Jacobian with respect to the drone's own position is -dr/dd (none for a wake-only queue, ``fleet.wake_only``:
a known force at each node, whose networks see d as the drone above's horizontal distance and height). Without
``nb`` (the gate, the monitor, the layer's re-base) d is the newest network's input mean: where the model was
trained.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cfknode.models.input_bounds import stored_bounds
from cfknode.models.input_layouts import WAKE_INPUT_NAMES, about_the_axis
from cfknode.models.modelfile import N_IN, N_OUT, ModelFile
from cfknode.models.residual_check import stored_score


@dataclass(frozen=True)
class StackedLayer:
    weight_t: np.ndarray  # (p, in, out): activations (p, N, in) multiply on the left
    weight: np.ndarray  # (p, out, in): the same, for the reverse-mode Jacobian
    bias: np.ndarray  # (p, 1, out)


class ResidualQueue:
    """r(x, u) = sum_j w_j f_j(v, u) for a whole queue, networks stacked (numpy, float64)."""

    def __init__(self, layers: tuple[StackedLayer, ...], activation: str, n_networks: int,
                 neighbour_default: np.ndarray | None = None) -> None:
        self._layers = layers
        self._activation = activation
        self.n_networks = n_networks
        # The neighbour input's stand-in where no neighbour position is given; None: no neighbour input.
        self.neighbour_default = neighbour_default
        # Output biases are summed once: the weighted sum over networks of constants.
        self._out_bias = layers[-1].bias.sum(axis=0) if layers else np.zeros((1, N_OUT))
        # The networks see only the neighbour's relative position (trainer_process.online_normalisation).
        self.wake_only = False
        # ... as its horizontal distance and height (modelfile.WAKE_INPUT_NAMES): a jet about the drone above's axis.
        self.about_the_axis = False
        # cfknode train's held-out per-axis score beside the fast layer (residual_check.py); None: not stored.
        self.beyond_layer: np.ndarray | None = None
        # Per network, the inputs' range it was trained on, (p, 1, n_in) each (input_bounds.py); None: unbounded.
        self._low: np.ndarray | None = None
        self._high: np.ndarray | None = None

    @classmethod
    def from_model_file(cls, mf: ModelFile) -> ResidualQueue:
        if not mf.networks:
            return cls((), mf.activation, 0)
        default = mf.networks[-1].normalisation.input_mean[N_IN:].copy() if mf.takes_neighbour else None
        w_queue = mf.queue_weights
        n_layers = len(mf.hidden) + 1
        stacked = []
        for i in range(n_layers):
            ws, bs = [], []
            for j, net in enumerate(mf.networks):
                w, b = net.layers[i]
                norm = net.normalisation
                if i == 0:
                    # a = W (z - m) / s + b = (W / s) z + (b - (W / s) m)
                    w = w / norm.input_scale[None, :]
                    b = b - w @ norm.input_mean
                if i == n_layers - 1:
                    gain = w_queue[j] * norm.output_scale
                    w = gain[:, None] * w
                    b = gain * b
                ws.append(w)
                bs.append(b)
            weight = np.stack(ws)  # (p, out, in)
            stacked.append(
                StackedLayer(
                    weight_t=np.ascontiguousarray(weight.transpose(0, 2, 1)),
                    weight=np.ascontiguousarray(weight),
                    bias=np.stack(bs)[:, None, :],
                )
            )
        queue = cls(tuple(stacked), mf.activation, len(mf.networks), default)
        queue.wake_only = all(net.normalisation.wake_only for net in mf.networks)
        queue.about_the_axis = tuple(mf.inputs) == WAKE_INPUT_NAMES
        queue.beyond_layer = stored_score(mf.extra)
        bounds = stored_bounds(mf.extra, len(mf.networks))
        if bounds is not None and bounds.shape[2] == stacked[0].weight.shape[2]:
            queue._low, queue._high = bounds[:, None, 0, :], bounds[:, None, 1, :]
        return queue

    @property
    def layers(self) -> tuple[StackedLayer, ...]:
        """The folded, stacked layers (read-only views for other renderings, e.g. torch)."""
        return self._layers

    @property
    def output_bias(self) -> np.ndarray:
        """(1, 3): the summed output bias; the last layer's per-network biases are not used."""
        return self._out_bias

    @property
    def activation(self) -> str:
        return self._activation

    @property
    def is_zero(self) -> bool:
        """True for an empty queue (nominal model)."""
        return self.n_networks == 0

    @property
    def takes_neighbour(self) -> bool:
        """Whether the networks take the neighbour's relative position as well (docs/fleet.md#neighbour-input)."""
        return self.neighbour_default is not None

    def evaluate(self, x: np.ndarray, u: np.ndarray, nb: np.ndarray | None = None) -> np.ndarray:
        """Residual on v': (n, 3) for x (n, 6), u (n, 3); (3,) for single vectors. ``nb``: the
        neighbour's world position(s) for a queue with the neighbour input (None: ``neighbour_default``)."""
        x2, u2 = np.atleast_2d(x), np.atleast_2d(u)
        n = x2.shape[0]
        if self.is_zero:
            out = np.zeros((n, N_OUT))
        else:
            h = self._inputs(x2, u2, nb)  # (N, n_in), broadcast over the network axis by matmul
            if self._low is not None:  # each network where it saw data: (p, N, n_in)
                h = np.clip(h, self._low, self._high)
            for layer in self._layers[:-1]:
                h = _activate(np.matmul(h, layer.weight_t) + layer.bias, self._activation)
            out = np.matmul(h, self._layers[-1].weight_t).sum(axis=0) + self._out_bias
        return out if np.ndim(x) == 2 else out[0]

    def linearise(
        self, x_nodes: np.ndarray, u_nodes: np.ndarray, nb: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Affine expansion at each node: r(x, u) ~= c[k] + Jx[k] @ x + Ju[k] @ u.

        x_nodes (N, 6), u_nodes (N, 3) -> c (N, 3), Jx (N, 3, 6), Ju (N, 3, 3); ``c`` already
        includes -Jx x_bar - Ju u_bar, so the MPC uses the three arrays as they are. ``nb`` (N, 3):
        the neighbour's world position at each node, a known parameter (queues with the neighbour
        input; None: ``neighbour_default`` as the relative position, and no position Jacobian).
        """
        n = x_nodes.shape[0]
        jx = np.zeros((n, N_OUT, 6))
        if self.is_zero:
            return np.zeros((n, N_OUT)), jx, np.zeros((n, N_OUT, 3))
        z = self._inputs(x_nodes, u_nodes, nb)
        p = self.n_networks
        # Forward pass keeping each hidden layer's activation derivative, (p, N, h).
        h = z if self._low is None else np.clip(z, self._low, self._high)
        slopes = []
        for layer in self._layers[:-1]:
            h, slope = _activate_with_slope(np.matmul(h, layer.weight_t) + layer.bias, self._activation)
            slopes.append(slope)
        last = self._layers[-1]
        value = np.matmul(h, last.weight_t).sum(axis=0) + self._out_bias
        # Reverse mode (3 outputs < 6 inputs), per network and node:
        # G = W_L diag(s_L-1) W_L-1 ... diag(s_0) W_0, rows (node, output) flattened for one product.
        g = last.weight[:, None, :, :] * slopes[-1][:, :, None, :]  # (p, N, 3, h)
        g = g.reshape(p, n * N_OUT, -1)
        for i in range(len(self._layers) - 2, -1, -1):
            g = np.matmul(g, self._layers[i].weight)  # (p, N*3, h_in)
            if i > 0:
                g = (g.reshape(p, n, N_OUT, -1) * slopes[i - 1][:, :, None, :]).reshape(p, n * N_OUT, -1)
        if self._low is not None:  # held at the edge of a network's data: no slope along a clamped input
            inside = ((z > self._low) & (z < self._high)).astype(np.float64)  # (p, N, n_in)
            g = (g.reshape(p, n, N_OUT, -1) * inside[:, :, None, :]).reshape(p, n * N_OUT, -1)
        jz = g.sum(axis=0).reshape(n, N_OUT, z.shape[1])  # d r / d (v, u[, d])
        jx[:, :, 3:6] = jz[:, :, 0:3]
        ju = np.ascontiguousarray(jz[:, :, 3:6])
        c = value - np.matmul(jz[:, :, 0:N_IN], z[:, 0:N_IN, None])[:, :, 0]
        if z.shape[1] > N_IN and nb is not None and not self.wake_only:
            # d = nb - p with nb known: dr/dp = -dr/dd, so c gains +dr/dd p_bar (held d adds nothing to x's terms).
            # A wake-only queue is flown as a known force at each node, as the plant's own air model is
            # (sim_backend/air_model.py): given the slope of a jet a few cm wide the MPC works against it.
            jd = jz[:, :, N_IN:]
            jx[:, :, 0:3] = -jd
            c = c + np.matmul(jd, x_nodes[:, 0:3, None])[:, :, 0]
        return c, jx, ju

    def _inputs(self, x: np.ndarray, u: np.ndarray, nb: np.ndarray | None) -> np.ndarray:
        """Network input z = (v, u): translation invariant, never absolute position; with the neighbour
        input also d = nb - p (``nb`` given) or the stand-in ``neighbour_default``."""
        if self.neighbour_default is None:
            return np.concatenate((x[:, 3:6], u), axis=1)
        if nb is None:
            d = np.broadcast_to(self.neighbour_default, (x.shape[0], 3))
        else:
            d = np.atleast_2d(np.asarray(nb, dtype=np.float64)) - x[:, 0:3]
            if self.about_the_axis:
                d = about_the_axis(d)
        return np.concatenate((x[:, 3:6], u, d), axis=1)


def _activate(a: np.ndarray, kind: str) -> np.ndarray:
    if kind == "tanh":
        return np.tanh(a, out=a)
    if kind == "softplus":
        return np.logaddexp(a, 0.0, out=a)
    if kind == "relu":
        return np.maximum(a, 0.0, out=a)
    raise ValueError(f"unknown activation {kind!r}")


def _activate_with_slope(a: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray]:
    if kind == "tanh":
        h = np.tanh(a, out=a)
        return h, 1.0 - h * h
    if kind == "softplus":
        # d softplus / da = sigmoid(a), written with tanh so it cannot overflow.
        slope = 0.5 * (1.0 + np.tanh(0.5 * a))
        return np.logaddexp(a, 0.0, out=a), slope
    if kind == "relu":
        slope = (a > 0.0).astype(np.float64)
        return np.maximum(a, 0.0, out=a), slope
    raise ValueError(f"unknown activation {kind!r}")


__all__ = ["ResidualQueue", "StackedLayer"]
