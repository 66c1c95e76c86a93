"""The CasADi rendering of a KNODE queue (weights as parameters) equals the torch and numpy ones."""

import numpy as np
import pytest

pytest.importorskip("torch")

from cfknode.models.knode import from_torch_queue, residual_numpy  # noqa: E402
from cfknode.models.knode_casadi import casadi_residual, pack_parameters, parameter_size  # noqa: E402
from cfknode.models.residual_np import ResidualQueue  # noqa: E402
from tests.test_residual_np import random_points, random_queue  # noqa: E402


@pytest.mark.parametrize("activation", ["tanh", "softplus", "relu"])
@pytest.mark.parametrize("n_nets", [1, 2, 3])
def test_casadi_matches_torch_to_1e9(activation, n_nets):
    queue = random_queue(n_nets, activation)
    mf = from_torch_queue(queue)
    f = casadi_residual(mf.hidden, mf.activation, mf.queue_size)
    theta = pack_parameters(mf)
    x, u = random_points(50)
    expected = residual_numpy(queue, x, u)
    got = np.array([np.array(f(x[i], u[i], theta)).ravel() for i in range(len(x))])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ResidualQueue.from_model_file(mf).evaluate(x, u), got, rtol=0, atol=1e-9)


def test_a_new_model_is_a_parameter_write():
    # One Function serves every queue length up to queue_size: swapping models changes theta only.
    small, full = from_torch_queue(random_queue(1, "tanh", seed=3)), from_torch_queue(random_queue(3, "tanh", seed=4))
    f = casadi_residual(full.hidden, full.activation, full.queue_size)
    assert pack_parameters(small).shape == pack_parameters(full).shape == (parameter_size(full.hidden, 3),)
    x, u = random_points(5)
    for mf in (small, full):
        q = ResidualQueue.from_model_file(mf)
        for i in range(5):
            np.testing.assert_allclose(np.array(f(x[i], u[i], pack_parameters(mf))).ravel(), q.evaluate(x[i], u[i]),
                                       atol=1e-9)


def test_empty_queue_is_zero_and_oversized_queue_is_refused():
    mf = from_torch_queue(random_queue(3, "tanh"))
    empty = type(mf)(mf.hidden, mf.activation, mf.queue_size, ())
    f = casadi_residual(mf.hidden, mf.activation, mf.queue_size)
    assert np.all(np.array(f(np.ones(6), np.ones(3), pack_parameters(empty))) == 0.0)
    with pytest.raises(ValueError):
        pack_parameters(mf, queue_size=2)
