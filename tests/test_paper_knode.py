"""Full-state KNODE: queue semantics, numpy rendering, data pairing and the training paths."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from cfknode.models.modelfile import queue_weights
from cfknode.app.bench.paper.rigid_body_knode import (
    NumpyResidual,
    OneStepPairs,
    ResidualLayout,
    RigidBodyQueue,
    TrainSettings,
    residual_error,
    fit_output_layer,
    train_newest,
)
from cfknode.app.bench.paper.protocol import PaperPlant, PaperProtocol
from cfknode.app.bench.paper.vehicle import PAPER_VEHICLE


def _z(rng: np.random.Generator, n: int) -> np.ndarray:
    z = rng.normal(size=(n, 17)) * 0.3
    z[:, 6:10] += (1.0, 0.0, 0.0, 0.0)
    z[:, 13] = rng.uniform(0.15, 0.45, n)
    z[:, 14:] *= 1e-3
    return z


@pytest.mark.parametrize("layout", [ResidualLayout.paper(), ResidualLayout.default()])
def test_numpy_residual_equals_torch_and_its_jacobian(layout):
    q = RigidBodyQueue(layout, torch.float64, seed=1)
    for _ in range(4):
        q.push()
    with torch.no_grad():
        for net in q.networks:
            net.l2.weight.normal_(0.0, 0.2, generator=torch.Generator().manual_seed(2))
            net.l2.bias.normal_(0.0, 0.1, generator=torch.Generator().manual_seed(3))
    res = NumpyResidual(q.to_weights())
    z = _z(np.random.default_rng(0), 6)
    with torch.no_grad():
        ref = q.residual(torch.as_tensor(z)).numpy()
    r, jac = res.value_and_jacobian(z)
    np.testing.assert_allclose(r, ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(res.value(z), r, atol=1e-14)
    for i in range(17):
        step = 1e-6 * max(1e-3, float(np.mean(np.abs(z[:, i]))))
        zp, zm = z.copy(), z.copy()
        zp[:, i] += step
        zm[:, i] -= step
        fd = (res.value(zp) - res.value(zm)) / (2 * step)
        np.testing.assert_allclose(jac[:, :, i], fd, rtol=1e-5, atol=1e-6 * (1 + np.abs(fd).max()))
    if layout.inputs[0] == 3:  # translation invariant: no position dependence at all
        assert np.all(jac[:, :, 0:3] == 0.0)


def test_queue_keeps_p_networks_freezes_the_old_and_weighs_them():
    layout = ResidualLayout.paper()
    q = RigidBodyQueue(layout, torch.float64, seed=0)
    nets = [q.push() for _ in range(4)]
    assert len(q) == 3 and q.networks[0] is nets[1]  # the oldest left
    assert [all(p.requires_grad for p in n.parameters()) for n in q.networks] == [False, False, True]
    z = torch.as_tensor(_z(np.random.default_rng(1), 3))
    w = queue_weights(3)
    np.testing.assert_allclose(w, [np.exp(-2), np.exp(-1), 1.0])
    with torch.no_grad():
        expected = sum(float(wk) * n(z) for wk, n in zip(w, q.networks))
        np.testing.assert_allclose(q.residual(z).numpy(), expected.numpy(), rtol=1e-12)
    copied = q.push(copy_from_newest=True)
    with torch.no_grad():
        np.testing.assert_allclose(copied(z).numpy(), nets[-1](z).numpy())
    back = RigidBodyQueue.from_weights(q.to_weights(), torch.float64)
    with torch.no_grad():
        np.testing.assert_allclose(back.residual(z).numpy(), q.residual(z).numpy(), rtol=1e-12)
    fresh = RigidBodyQueue(ResidualLayout.default(), torch.float64)
    assert torch.all(fresh.push().l2.weight == 0)  # cfknode's fresh network is "no residual"


def test_paper_rows_pair_as_the_original():
    rows = np.arange(4 * 17, dtype=float).reshape(4, 17)  # [x_{k+1}, u_k]
    pairs = OneStepPairs.from_paper_rows(rows)
    np.testing.assert_array_equal(pairs.z0, rows[:3])  # row j's input is used ...
    np.testing.assert_array_equal(pairs.x1, rows[1:, :13])  # ... to reach row j+1's state
    states = np.arange(5 * 13, dtype=float).reshape(5, 13)
    inputs = np.arange(4 * 4, dtype=float).reshape(4, 4)
    aligned = OneStepPairs.aligned(states, inputs)
    np.testing.assert_array_equal(aligned.z0[:, 13:], inputs)
    np.testing.assert_array_equal(aligned.x1, states[1:])
    head, tail = aligned.split(0.25)
    assert len(head) == 3 and len(tail) == 1


def _light_plant_pairs(n: int, seed: int) -> OneStepPairs:
    """Steps of the paper's plant flying at 0.015 kg (half the nominal mass) with varied inputs."""
    plant = PaperPlant(PaperProtocol())
    plant.mass = 0.015
    rng = np.random.default_rng(seed)
    states, inputs = [plant.state.copy()], []
    for _ in range(n):
        u = np.array([rng.uniform(0.12, 0.18), *rng.normal(0.0, 2e-6, 3)])
        inputs.append(u)
        states.append(plant.step(u).copy())
    return OneStepPairs.aligned(np.asarray(states), np.asarray(inputs))


def test_training_learns_a_mass_change():
    pairs = _light_plant_pairs(120, seed=0)
    phys = PAPER_VEHICLE
    for layout, settings in (
        (ResidualLayout.paper(), TrainSettings(epochs=80, lr=0.01, loss="paper")),
        (ResidualLayout.default(), TrainSettings(epochs=80, lr=0.01, loss="residual")),
    ):
        q = RigidBodyQueue(layout, torch.float32, seed=0)
        before = residual_error(q, pairs, 0.002, phys)  # empty queue: the nominal model
        q.push()
        stats = train_newest(q, pairs, settings, phys)
        assert stats.loss_last < 0.2 * stats.loss_first
        assert residual_error(q, pairs, 0.002, phys) < 0.05 * before


def test_output_layer_fit_recovers_the_residual_in_one_solve():
    pairs = _light_plant_pairs(80, seed=1)
    phys = PAPER_VEHICLE
    layout = ResidualLayout.default()
    q = RigidBodyQueue(layout, torch.float64, seed=0)
    q.push()
    nominal = residual_error(q, pairs, 0.002, phys)  # zero output layer: nominal
    fit_output_layer(q, pairs, 0.002, phys, ridge=1e-3)
    assert residual_error(q, pairs, 0.002, phys) < 1e-3 * nominal
    # A large ridge keeps the output layer where it was (the warm start).
    q2 = RigidBodyQueue(layout, torch.float64, seed=0)
    q2.push()
    fit_output_layer(q2, pairs, 0.002, phys, ridge=1e9)
    assert float(q2.networks[-1].l2.weight.detach().abs().max()) < 1e-6


def test_layout_validation():
    with pytest.raises(ValueError):
        ResidualLayout(inputs=(0, 1), rows=(3,), input_scale=(1.0,))
    with pytest.raises(ValueError):
        ResidualLayout(inputs=(17,), rows=(3,))
    assert replace(ResidualLayout.default(), hidden=8).hidden == 8
    with pytest.raises(ValueError):
        train_newest(RigidBodyQueue(ResidualLayout.paper()), _light_plant_pairs(3, 0), TrainSettings(), PAPER_VEHICLE)
