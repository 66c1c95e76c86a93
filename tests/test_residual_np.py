"""numpy rendering of the KNODE queue: agreement with torch, Jacobians, affine form, no torch import."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from cfknode.models.knode import KnodeQueue, from_torch_queue, residual_numpy
from cfknode.models.modelfile import Normalisation
from cfknode.models.residual_np import ResidualQueue


def random_queue(n: int, activation: str, hidden: tuple[int, ...] = (32, 32), queue_size: int = 3, seed: int = 0,
                 n_in: int = 6) -> KnodeQueue:
    """``n`` networks of random weights; ``n_in`` inputs (9 with the neighbour input)."""
    rng = np.random.default_rng(seed)
    norm = Normalisation(rng.normal(size=n_in) * 0.3, rng.uniform(0.3, 3.0, n_in), rng.uniform(0.5, 3.0, 3))
    q = KnodeQueue(hidden, activation, queue_size, norm, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(n):
        net = q.push()
        with torch.no_grad():
            for layer in net.layers:
                layer.weight.copy_(torch.randn(layer.weight.shape, generator=gen, dtype=torch.float64) * 0.4)
                layer.bias.copy_(torch.randn(layer.bias.shape, generator=gen, dtype=torch.float64) * 0.3)
    return q


def random_points(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 6)) * 1.5, rng.normal(size=(n, 3)) * 4.0


@pytest.mark.parametrize("activation", ["tanh", "softplus", "relu"])
@pytest.mark.parametrize("n_nets", [1, 3])
def test_numpy_matches_torch(activation: str, n_nets: int) -> None:
    q = random_queue(n_nets, activation)
    rq = ResidualQueue.from_model_file(from_torch_queue(q))
    x, u = random_points(200)
    np.testing.assert_allclose(rq.evaluate(x, u), residual_numpy(q, x, u), rtol=0.0, atol=1e-9)
    single = rq.evaluate(x[0], u[0])
    assert single.shape == (3,)
    np.testing.assert_allclose(single, residual_numpy(q, x[:1], u[:1])[0], rtol=0.0, atol=1e-9)


def test_softplus_agrees_far_from_the_origin() -> None:
    # torch's F.softplus turns linear above 20; the queue must use the exact function numpy uses.
    q = random_queue(2, "softplus")
    rq = ResidualQueue.from_model_file(from_torch_queue(q))
    x, u = random_points(50)
    np.testing.assert_allclose(rq.evaluate(x * 30, u * 30), residual_numpy(q, x * 30, u * 30), rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("activation", ["tanh", "softplus", "relu"])
def test_jacobians_match_autograd(activation: str) -> None:
    q = random_queue(3, activation)
    rq = ResidualQueue.from_model_file(from_torch_queue(q))
    x, u = random_points(20)
    c, jx, ju = rq.linearise(x, u)
    assert c.shape == (20, 3) and jx.shape == (20, 3, 6) and ju.shape == (20, 3, 3)
    xt, ut = torch.as_tensor(x), torch.as_tensor(u)
    jac_x, jac_u = torch.func.vmap(torch.func.jacrev(lambda a, b: q(a, b), argnums=(0, 1)))(xt, ut)
    np.testing.assert_allclose(jx, jac_x.detach().numpy(), rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(ju, jac_u.detach().numpy(), rtol=0.0, atol=1e-9)
    np.testing.assert_array_equal(jx[:, :, 0:3], 0.0)  # no dependence on absolute position


@pytest.mark.parametrize("activation", ["tanh", "softplus"])
def test_jacobians_match_finite_differences(activation: str) -> None:
    rq = ResidualQueue.from_model_file(from_torch_queue(random_queue(3, activation)))
    x, u = random_points(10)
    _, jx, ju = rq.linearise(x, u)
    h = 1e-6
    for i in range(6):
        d = np.zeros(6)
        d[i] = h
        fd = (rq.evaluate(x + d, u) - rq.evaluate(x - d, u)) / (2 * h)
        np.testing.assert_allclose(jx[:, :, i], fd, rtol=1e-6, atol=1e-7)
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        fd = (rq.evaluate(x, u + d) - rq.evaluate(x, u - d)) / (2 * h)
        np.testing.assert_allclose(ju[:, :, i], fd, rtol=1e-6, atol=1e-7)


def test_affine_form_reproduces_the_value_and_is_first_order() -> None:
    rq = ResidualQueue.from_model_file(from_torch_queue(random_queue(3, "tanh")))
    xb, ub = random_points(20)
    c, jx, ju = rq.linearise(xb, ub)

    def affine(x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return c + np.einsum("kij,kj->ki", jx, x) + np.einsum("kij,kj->ki", ju, u)

    np.testing.assert_allclose(affine(xb, ub), rq.evaluate(xb, ub), rtol=0.0, atol=1e-12)
    rng = np.random.default_rng(7)
    dx, du = rng.normal(size=(20, 6)), rng.normal(size=(20, 3))
    errs = [np.abs(affine(xb + e * dx, ub + e * du) - rq.evaluate(xb + e * dx, ub + e * du)).max() for e in (1e-2, 5e-3)]
    assert errs[1] < errs[0] / 3.0  # the remainder shrinks like eps^2


def test_matches_the_mpc_expansion_about_the_nodes() -> None:
    # flight/mpc.py builds c from (value, J, point) as value - Jx x_bar - Ju u_bar; ours must equal it.
    rq = ResidualQueue.from_model_file(from_torch_queue(random_queue(2, "tanh")))
    xb, ub = random_points(20)
    c, jx, ju = rq.linearise(xb, ub)
    value = rq.evaluate(xb, ub)
    np.testing.assert_allclose(c, value - np.einsum("kij,kj->ki", jx, xb) - np.einsum("kij,kj->ki", ju, ub), atol=1e-12)


def test_empty_queue_is_zero() -> None:
    rq = ResidualQueue.from_model_file(from_torch_queue(KnodeQueue((8,), "tanh", 3)))
    x, u = random_points(5)
    assert rq.is_zero
    np.testing.assert_array_equal(rq.evaluate(x, u), 0.0)
    for arr, shape in zip(rq.linearise(x, u), [(5, 3), (5, 3, 6), (5, 3, 3)]):
        assert arr.shape == shape and not arr.any()


def test_fresh_pushed_network_changes_nothing_but_the_weights() -> None:
    q = random_queue(2, "tanh")
    before = ResidualQueue.from_model_file(from_torch_queue(q))
    q.push()
    after = ResidualQueue.from_model_file(from_torch_queue(q))
    x, u = random_points(30)
    np.testing.assert_allclose(after.evaluate(x, u), np.exp(-1.0) * before.evaluate(x, u), rtol=1e-12, atol=1e-12)


def test_module_imports_without_torch(tmp_path) -> None:
    from cfknode.models.modelfile import save_model

    path = save_model(tmp_path / "m.safetensors", from_torch_queue(random_queue(3, "tanh")))
    code = (
        "import sys, numpy as np\n"
        "from cfknode.models.residual_np import ResidualQueue\n"
        "from cfknode.models.modelfile import load_model\n"
        f"rq = ResidualQueue.from_model_file(load_model({str(path)!r}))\n"
        "c, jx, ju = rq.linearise(np.zeros((20, 6)), np.zeros((20, 3)))\n"
        "assert np.all(np.isfinite(c))\n"
        "bad = sorted(m for m in sys.modules if m == 'torch' or m.startswith('torch.'))\n"
        "print('TORCH' if bad else 'CLEAN', bad[:3])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("CLEAN"), out.stdout
