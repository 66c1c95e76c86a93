"""The nominal model's numpy, CasADi and torch renderings agree, and hover is an equilibrium."""

import numpy as np
import pytest

from cfknode.models import quadrotor as qm

INERTIA = (1.66e-5, 1.67e-5, 2.93e-5)


def _random_states(rng, n):
    x = rng.normal(size=(n, 13))
    x[:, 6:10] /= np.linalg.norm(x[:, 6:10], axis=1, keepdims=True)
    return x


def test_rigid_body_numpy_casadi_torch_agree():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(0)
    xs, us = _random_states(rng, 50), rng.normal(size=(50, 4)) * [0.3, 1e-4, 1e-4, 1e-5]
    f_ca = qm.casadi_rigid_body(INERTIA, 9.81)
    batched = qm.rigid_body_rhs(xs, us, 0.03, INERTIA, 9.81)
    via_torch = qm.rigid_body_rhs(torch.tensor(xs), torch.tensor(us), 0.03, INERTIA, 9.81, qm.torch_backend()).numpy()
    for i in range(len(xs)):
        np.testing.assert_allclose(np.array(f_ca(xs[i], us[i], 0.03)).ravel(), batched[i], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(via_torch, batched, rtol=1e-12, atol=1e-12)


def test_translational_numpy_casadi_agree():
    rng = np.random.default_rng(1)
    f_ca = qm.casadi_translational()
    for _ in range(20):
        x, u = rng.normal(size=6), rng.normal(size=3)
        np.testing.assert_allclose(np.array(f_ca(x, u)).ravel(), qm.translational_rhs(x, u), atol=1e-15)


def test_hover_is_an_equilibrium():
    x = np.zeros(13)
    x[6] = 1.0
    xdot = qm.rigid_body_rhs(x, qm.hover_input(0.029, 9.81), 0.029, INERTIA, 9.81)
    np.testing.assert_allclose(xdot, 0.0, atol=1e-15)


def test_thrust_tilts_acceleration_with_attitude():
    # Pitch +10 deg (right-handed, nose down) tilts thrust toward +x.
    q = qm.euler_zyx_to_quat(0.0, np.deg2rad(10), 0.0)
    x = np.concatenate((np.zeros(6), q, np.zeros(3)))
    xdot = qm.rigid_body_rhs(x, np.array([0.3, 0, 0, 0]), 0.03, INERTIA, 9.81)
    assert xdot[3] > 0 and abs(xdot[4]) < 1e-12


def test_euler_roundtrip_and_rotation():
    rng = np.random.default_rng(2)
    for _ in range(20):
        rpy = rng.uniform([-1, -1.2, -3], [1, 1.2, 3])
        q = qm.euler_zyx_to_quat(*rpy)
        np.testing.assert_allclose(qm.quat_to_euler_zyx(q), rpy, atol=1e-12)
        R = qm.quat_to_rotation(q)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(R[:, 2], qm.thrust_direction(*q), atol=1e-12)


def test_rk4_step_is_fourth_order():
    f = lambda x, u: -x  # noqa: E731
    errs = [abs(qm.rk4_step(f, 1.0, None, h) - np.exp(-h)) for h in (0.1, 0.05)]
    assert errs[0] / errs[1] == pytest.approx(32, rel=0.1)
