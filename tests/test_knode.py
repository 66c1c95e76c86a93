"""KNODE torch queue: forgetting weights, freezing, push/drop, warm start, residual only on v'."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cfknode.app.config import load_config
from cfknode.models.knode import KnodeQueue, ResidualNet, TrainingResidual, from_torch_queue, residual_numpy, to_torch_queue
from cfknode.models.modelfile import Normalisation
from cfknode.models.quadrotor import torch_backend, translational_rhs


def randomise(net: ResidualNet, seed: int) -> None:
    """Give every layer (the zero output layer too) random weights, so the net is not trivial."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for layer in net.layers:
            layer.weight.copy_(torch.randn(layer.weight.shape, generator=gen, dtype=layer.weight.dtype) * 0.5)
            layer.bias.copy_(torch.randn(layer.bias.shape, generator=gen, dtype=layer.bias.dtype) * 0.3)


def make_queue(n: int, queue_size: int = 3, activation: str = "tanh") -> KnodeQueue:
    norm = Normalisation(np.array([0.1, -0.2, 0.0, 0.5, 0.0, -1.0]), np.array([0.5, 0.5, 0.4, 2.0, 2.0, 3.0]), np.array([1.5, 1.0, 2.0]))
    q = KnodeQueue((16, 8), activation, queue_size, norm, seed=0)
    for k in range(n):
        randomise(q.push(), seed=100 + k)
    return q


def inputs(n: int = 40, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    return torch.as_tensor(rng.normal(size=(n, 6))), torch.as_tensor(rng.normal(size=(n, 3)) * 3.0)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_forgetting_weights_are_e_to_k_minus_len(n: int) -> None:
    q = make_queue(n)
    w = q.weights().numpy()
    assert w.shape == (n,)
    np.testing.assert_allclose(w, [math.exp(k - n) for k in range(1, n + 1)], rtol=1e-15)
    assert w[-1] == 1.0


def test_queue_output_is_the_weighted_sum_of_its_networks() -> None:
    q = make_queue(3)
    x, u = inputs()
    z = torch.cat((x[:, 3:6], u), dim=1)
    with torch.no_grad():
        expected = sum(math.exp(k - 2) * net(z) for k, net in enumerate(q.networks))
        np.testing.assert_allclose(q(x, u).numpy(), expected.numpy(), rtol=1e-13, atol=1e-13)


def test_only_the_newest_network_is_trainable() -> None:
    q = make_queue(3)
    for k, net in enumerate(q.networks):
        assert all(p.requires_grad == (k == 2) for p in net.parameters())
    assert {id(p) for p in q.trainable_parameters()} == {id(p) for p in q.newest.parameters()}
    x, u = inputs()
    q(x, u).pow(2).sum().backward()
    assert all(p.grad is None for net in list(q.networks)[:2] for p in net.parameters())
    assert all(p.grad is not None and torch.any(p.grad != 0) for p in q.newest.parameters())


def test_push_on_a_full_queue_drops_the_oldest() -> None:
    q = make_queue(3, queue_size=3)
    before = list(q.networks)
    new = q.push()
    assert len(q) == 3
    assert list(q.networks) == [before[1], before[2], new]
    assert all(not p.requires_grad for p in before[2].parameters())
    assert all(p.requires_grad for p in new.parameters())


def test_fresh_network_adds_no_residual() -> None:
    q = make_queue(2)
    x, u = inputs()
    with torch.no_grad():
        before = q(x, u).clone()
        q.push()
        # The new net is zero; the old ones are re-weighted by the longer queue (e^-1 each step back).
        expected = math.exp(-1.0) * before
        np.testing.assert_allclose(q(x, u).numpy(), expected.numpy(), rtol=1e-13, atol=1e-13)
        np.testing.assert_array_equal(q.newest(torch.cat((x[:, 3:6], u), dim=1)).numpy(), 0.0)


def test_warm_start_copies_the_newest_and_is_independent() -> None:
    q = make_queue(2)
    x, u = inputs()
    z = torch.cat((x[:, 3:6], u), dim=1)
    old_newest = q.newest
    with torch.no_grad():
        ref = old_newest(z).clone()
    new = q.push(copy_from_newest=True)
    assert new is not old_newest
    with torch.no_grad():
        np.testing.assert_array_equal(new(z).numpy(), ref.numpy())
        np.testing.assert_array_equal(new.input_scale.numpy(), old_newest.input_scale.numpy())
        new.layers[0].weight.add_(1.0)
        np.testing.assert_array_equal(old_newest(z).numpy(), ref.numpy())
    with pytest.raises(ValueError, match="normalisation"):
        q.push(copy_from_newest=True, normalisation=Normalisation.identity())


def test_empty_queue_is_the_nominal_model() -> None:
    q = KnodeQueue((8,), "tanh", 2)
    x, u = inputs()
    assert len(q) == 0
    np.testing.assert_array_equal(q(x, u).numpy(), 0.0)
    np.testing.assert_array_equal(q.rhs(x, u).numpy(), translational_rhs(x, u, torch_backend()).numpy())
    assert list(q.trainable_parameters()) == []


def test_residual_acts_on_v_dot_only_and_ignores_position() -> None:
    q = make_queue(3)
    x, u = inputs()
    with torch.no_grad():
        f = q.rhs(x, u)
        nominal = translational_rhs(x, u, torch_backend())
        np.testing.assert_array_equal(f[:, 0:3].numpy(), x[:, 3:6].numpy())  # p' = v exactly
        np.testing.assert_allclose((f - nominal)[:, 3:6].numpy(), q(x, u).numpy(), rtol=1e-14, atol=1e-14)
        shifted = x.clone()
        shifted[:, 0:3] += torch.tensor([5.0, -3.0, 2.0], dtype=x.dtype)
        np.testing.assert_array_equal(q(shifted, u).numpy(), q(x, u).numpy())


def test_normalisation_is_applied() -> None:
    norm = Normalisation(np.arange(6.0), np.linspace(0.5, 3.0, 6), np.array([2.0, 3.0, 4.0]))
    net = ResidualNet((8,), "tanh", norm)
    randomise(net, 3)
    plain = ResidualNet((8,), "tanh", Normalisation.identity())
    plain.load_state_dict({k: v for k, v in net.state_dict().items() if k.startswith("layers")}, strict=False)
    z = torch.as_tensor(np.random.default_rng(1).normal(size=(10, 6)))
    with torch.no_grad():
        expected = plain((z - torch.arange(6.0, dtype=z.dtype)) / torch.linspace(0.5, 3.0, 6, dtype=z.dtype))
        expected = expected * torch.tensor([2.0, 3.0, 4.0], dtype=z.dtype)
        np.testing.assert_allclose(net(z).numpy(), expected.numpy(), rtol=1e-13, atol=1e-13)


def test_seeded_initialisation_is_reproducible() -> None:
    def first_layer(seed: int) -> np.ndarray:
        q = KnodeQueue((16,), "tanh", 3, seed=seed)
        q.push()
        return q.newest.layers[0].weight.detach().numpy().copy()

    np.testing.assert_array_equal(first_layer(4), first_layer(4))
    assert not np.array_equal(first_layer(4), first_layer(5))


def test_from_config_uses_the_knode_section() -> None:
    cfg = load_config(overrides={"knode.hidden": [12, 7], "knode.activation": "softplus", "knode.queue_size": 4})
    q = KnodeQueue.from_config(cfg.knode)
    q.push()
    assert (q.hidden, q.activation, q.queue_size) == ((12, 7), "softplus", 4)
    assert [tuple(layer.weight.shape) for layer in q.newest.layers] == [(12, 6), (7, 12), (3, 7)]


@pytest.mark.parametrize("activation", ["tanh", "softplus", "relu"])
def test_model_file_conversion_round_trips(activation: str) -> None:
    q = make_queue(3, activation=activation)
    mf = from_torch_queue(q)
    assert len(mf.networks) == 3 and mf.activation == activation
    back = to_torch_queue(mf)
    x, u = inputs()
    np.testing.assert_array_equal(residual_numpy(back, x.numpy(), u.numpy()), residual_numpy(q, x.numpy(), u.numpy()))
    assert [any(p.requires_grad for p in net.parameters()) for net in back.networks] == [False, False, True]
    back.push(copy_from_newest=True)  # a loaded queue continues like the original
    assert len(back) == 3


@pytest.mark.parametrize("n", [1, 3])
def test_training_residual_equals_the_queue_with_the_same_gradients(n: int) -> None:
    q = make_queue(n, activation="softplus")
    fast = TrainingResidual(q)
    x, u = inputs()
    x.requires_grad_(True)
    ref = q(x, u)
    out = fast(x, u)
    np.testing.assert_allclose(out.detach().numpy(), ref.detach().numpy(), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(fast.rhs(x, u).detach().numpy(), q.rhs(x, u).detach().numpy(), rtol=1e-12, atol=1e-12)
    params = list(q.trainable_parameters())
    g_ref = torch.autograd.grad(ref.pow(2).sum(), [x, *params])
    g_fast = torch.autograd.grad(out.pow(2).sum(), [x, *params])
    for a, b in zip(g_ref, g_fast):
        np.testing.assert_allclose(b.numpy(), a.numpy(), rtol=1e-10, atol=1e-10)
    assert all(not b.requires_grad for b in fast.buffers())
