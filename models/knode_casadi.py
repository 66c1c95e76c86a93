"""The KNODE residual queue rendered in CasADi, with every weight a symbolic parameter.

The flight MPC never differentiates the networks inside CasADi (it takes a numpy
linearisation per tick, see ``flight/model_slot.py``); this rendering is for converged
reference solves and for checking that the three renderings (torch, numpy, CasADi) are
one model. The parameter vector has a fixed size for ``queue_size`` networks, so a queue
of any length up to that, or a new model, is a parameter write and never a rebuild:
an empty slot has forgetting weight 0 and unit scales.
"""

from __future__ import annotations

from typing import Any, Sequence

import casadi as ca
import numpy as np

from cfknode.models.modelfile import N_IN, N_OUT, ModelFile

_NORM = 2 * N_IN + N_OUT  # input mean, input scale, output scale


def _layer_sizes(hidden: Sequence[int]) -> list[tuple[int, int]]:
    sizes = [N_IN, *hidden, N_OUT]
    return list(zip(sizes[1:], sizes[:-1]))  # (out, in) per layer


def network_parameter_size(hidden: Sequence[int]) -> int:
    return _NORM + sum(o * i + o for o, i in _layer_sizes(hidden))


def parameter_size(hidden: Sequence[int], queue_size: int) -> int:
    """Length of theta: ``queue_size`` networks, then their ``queue_size`` forgetting weights."""
    return queue_size * (network_parameter_size(hidden) + 1)


def pack_parameters(mf: ModelFile, queue_size: int | None = None) -> np.ndarray:
    """theta for ``casadi_residual``: the file's networks (oldest first) in the leading slots."""
    slots = mf.queue_size if queue_size is None else queue_size
    if len(mf.networks) > slots:
        raise ValueError(f"model has {len(mf.networks)} networks, more than {slots} slots")
    per_net = network_parameter_size(mf.hidden)
    theta = np.zeros(parameter_size(mf.hidden, slots))
    for j in range(slots):
        block = theta[j * per_net : (j + 1) * per_net]
        if j < len(mf.networks):
            net = mf.networks[j]
            norm = net.normalisation
            parts = [norm.input_mean, norm.input_scale, norm.output_scale]
            for w, b in net.layers:
                parts += [np.asarray(w).ravel(order="F"), np.asarray(b)]  # CasADi reshapes column-major
            block[:] = np.concatenate(parts)
        else:
            block[N_IN : 2 * N_IN] = 1.0  # unit scales keep an empty slot finite
            block[2 * N_IN : _NORM] = 1.0
    theta[slots * per_net : slots * per_net + len(mf.networks)] = mf.queue_weights
    return theta


def _activation(a: Any, kind: str) -> Any:
    if kind == "tanh":
        return ca.tanh(a)
    if kind == "softplus":
        return ca.log1p(ca.exp(-ca.fabs(a))) + ca.fmax(a, 0)  # overflow-free log(1 + e^a)
    if kind == "relu":
        return ca.fmax(a, 0)
    raise ValueError(f"unknown activation {kind!r}")


def residual_expression(x: Any, u: Any, theta: Any, hidden: Sequence[int], activation: str, queue_size: int) -> Any:
    """r(x, u; theta) on v' as a CasADi expression (x: 6, u: 3, theta: ``parameter_size``)."""
    z = ca.vertcat(x[3], x[4], x[5], u[0], u[1], u[2])  # (v, u): never absolute position
    per_net = network_parameter_size(hidden)
    weights = theta[queue_size * per_net :]
    total = ca.MX.zeros(N_OUT, 1) if isinstance(theta, ca.MX) else ca.SX.zeros(N_OUT, 1)
    for j in range(queue_size):
        block = theta[j * per_net : (j + 1) * per_net]
        mean, scale, out_scale = block[0:N_IN], block[N_IN : 2 * N_IN], block[2 * N_IN : _NORM]
        h = (z - mean) / scale
        k = _NORM
        layers = _layer_sizes(hidden)
        for i, (n_out, n_in) in enumerate(layers):
            w = ca.reshape(block[k : k + n_out * n_in], n_out, n_in)
            k += n_out * n_in
            b = block[k : k + n_out]
            k += n_out
            h = ca.mtimes(w, h) + b
            if i < len(layers) - 1:
                h = _activation(h, activation)
        total = total + weights[j] * (h * out_scale)
    return total


def casadi_residual(hidden: Sequence[int], activation: str, queue_size: int) -> Any:
    """CasADi Function r(x[6], u[3], theta) -> residual acceleration on v' [3]."""
    x, u = ca.SX.sym("x", 6), ca.SX.sym("u", 3)
    theta = ca.SX.sym("theta", parameter_size(hidden, queue_size))
    r = residual_expression(x, u, theta, hidden, activation, queue_size)
    return ca.Function("knode_residual", [x, u, theta], [r], ["x", "u", "theta"], ["r"])
