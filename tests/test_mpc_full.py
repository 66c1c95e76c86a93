"""Full-state MPC: hand-written Jacobians, the numpy hybrid RK4, and exactness against the network
inside the CasADi graph."""

from __future__ import annotations

from dataclasses import replace

import casadi as ca
import numpy as np
import pytest
import torch

from cfknode.app.bench.paper.mpc_full import (
    FullMpcSpec,
    FullStateMpc,
    HybridRk4,
    rigid_body_rhs_jacobian,
)
from cfknode.models.quadrotor import NUMPY, casadi_backend, rigid_body_rhs, rk4_step
from cfknode.app.bench.paper.rigid_body_knode import NumpyResidual, ResidualLayout, RigidBodyQueue
from cfknode.app.bench.paper.vehicle import PAPER_VEHICLE, plus_mixer

INERTIA = (1.43e-5, 1.43e-5, 2.89e-5)
G = 9.81


def _random_states(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    x = rng.normal(size=(n, 13))
    x[:, 6:10] /= np.linalg.norm(x[:, 6:10], axis=1, keepdims=True)
    u = np.column_stack((rng.uniform(0.1, 0.5, n), rng.normal(0, 1e-3, (n, 3))))
    return x, u


def _queue(layout: ResidualLayout, n_nets: int, seed: int, gain: float = 0.3) -> NumpyResidual:
    q = RigidBodyQueue(layout, torch.float64, seed=seed)
    for _ in range(n_nets):
        q.push()
    with torch.no_grad():
        for net in q.networks:
            net.l2.weight.mul_(gain)
            net.l2.bias.normal_(0.0, 0.05, generator=torch.Generator().manual_seed(seed))
    return NumpyResidual(q.to_weights())


def test_rhs_jacobian_matches_casadi():
    rng = np.random.default_rng(0)
    x, u = _random_states(rng, 7)
    f, jac, dm = rigid_body_rhs_jacobian(x, u, 0.031, INERTIA, G)
    xs, us, ms = ca.SX.sym("x", 13), ca.SX.sym("u", 4), ca.SX.sym("m")
    expr = rigid_body_rhs(xs, us, ms, INERTIA, G, casadi_backend())
    ref = ca.Function("ref", [xs, us, ms], [expr, ca.jacobian(expr, ca.vertcat(xs, us)), ca.jacobian(expr, ms)])
    for i in range(x.shape[0]):
        fr, jr, mr = (np.asarray(a) for a in ref(x[i], u[i], 0.031))
        np.testing.assert_allclose(f[i], fr.ravel(), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(jac[i], jr, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(dm[i], mr.ravel(), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(f, rigid_body_rhs(x, u, 0.031, INERTIA, G, NUMPY), atol=1e-12)


def _plan(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    x, u = _random_states(rng, n + 1)
    x[:, 10:13] *= 0.5
    w = np.concatenate([np.concatenate((u[k], x[k + 1])) for k in range(n)])
    return w, x[0]


def test_hybrid_rk4_defects_and_sensitivities():
    spec = FullMpcSpec(horizon=4, residual_rows=tuple(range(13)))
    dyn = HybridRk4(spec)
    res = _queue(ResidualLayout.paper(), 2, seed=1)
    dyn.set_residual(res)
    rng = np.random.default_rng(2)
    w, x0 = _plan(rng, spec.horizon)
    defects, sens = dyn.run(w, x0, 0.03, True)

    def hybrid(y: np.ndarray, uu: np.ndarray) -> np.ndarray:
        out = rigid_body_rhs(y, uu, 0.03, INERTIA, G, NUMPY)
        return out + res.value(np.concatenate((y, uu))[None])[0]

    stages = w.reshape(spec.horizon, 17)
    x_prev = x0
    for k in range(spec.horizon):
        y = x_prev
        for _ in range(spec.substeps):
            y = rk4_step(hybrid, y, stages[k, :4], spec.dt / spec.substeps)
        np.testing.assert_allclose(defects[k], stages[k, 4:] - y, atol=1e-10)
        x_prev = stages[k, 4:]
    # Central differences of F(x_k, u_k) = x_{k+1} - defect_k against the forward-mode sensitivities.
    k, eps = 2, 1e-6
    for col in (0, 4, 7, 11, 13, 15):
        wp, wm = w.copy(), w.copy()
        idx = 17 * (k - 1) + 4 + col if col < 13 else 17 * k + col - 13
        step = eps if col < 13 else eps * (1e-3 if col > 13 else 1.0)
        wp[idx] += step
        wm[idx] -= step
        fp = stages[k, 4:] - dyn.run(wp, x0, 0.03, False)[0][k]
        fm = stages[k, 4:] - dyn.run(wm, x0, 0.03, False)[0][k]
        fd = (fp - fm) / (2 * step)
        np.testing.assert_allclose(sens[k, :, col], fd, rtol=1e-5, atol=1e-6 * max(1.0, np.abs(fd).max()))
    fp = stages[k, 4:] - dyn.run(w, x0, 0.03 + 1e-7, False)[0][k]
    fm = stages[k, 4:] - dyn.run(w, x0, 0.03 - 1e-7, False)[0][k]
    np.testing.assert_allclose(sens[k, :, 17], (fp - fm) / 2e-7, rtol=1e-5, atol=1e-6)


def _hover_ref(n: int, p: tuple[float, float, float] = (1.0, 0.0, 0.5)) -> np.ndarray:
    x_ref = np.zeros((n, 13))
    x_ref[:, 0:3] = p
    x_ref[:, 6] = 1.0
    return x_ref


@pytest.fixture(scope="module")
def nominal() -> FullStateMpc:
    return FullStateMpc(FullMpcSpec(horizon=10))


def test_nominal_mpc_holds_hover_with_the_given_mass(nominal):
    n = nominal.horizon
    x0 = np.zeros(13)
    x0[0:3] = (1.0, 0.0, 0.5)
    x0[6] = 1.0
    for mass in (0.03, 0.045):
        u_ref = np.tile([mass * G, 0, 0, 0], (n, 1))
        sol = nominal.solve(x0, _hover_ref(n), u_ref, mass)
        assert sol.ok
        np.testing.assert_allclose(sol.u, [mass * G, 0, 0, 0], atol=1e-7)
        np.testing.assert_allclose(sol.x_pred[:, :3], np.tile(x0[:3], (n + 1, 1)), atol=1e-7)


def test_nominal_mpc_moves_toward_the_reference(nominal):
    n = nominal.horizon
    x0 = np.zeros(13)
    x0[6] = 1.0
    sol = nominal.solve(x0, _hover_ref(n, (0.0, 0.0, 0.3)), np.zeros((n, 4)), 0.03)
    assert sol.ok
    assert sol.u[0] > 0.03 * G  # climbs toward z = 0.3
    assert sol.x_pred[-1, 2] > 0.01


def test_input_scaling_and_rotor_polytope():
    mixer, force_max = plus_mixer(PAPER_VEHICLE), PAPER_VEHICLE.thrust_max_per_motor
    x0 = np.zeros(13)
    x0[6] = 1.0
    x0[10] = 30.0  # rolling fast: braking it needs more moment than the rotors can give
    ref = _hover_ref(6, (0.2, -0.1, 0.1))
    a = FullStateMpc(FullMpcSpec(horizon=6)).solve(x0, ref, np.zeros((6, 4)), 0.03)
    b = FullStateMpc(FullMpcSpec(horizon=6, input_scale=(0.1, 1e-3, 1e-3, 1e-3))).solve(x0, ref, np.zeros((6, 4)), 0.03)
    assert a.ok and b.ok
    np.testing.assert_allclose(a.u_pred, b.u_pred, rtol=1e-5, atol=1e-7)  # IPOPT sits ~1e-8 inside bounds
    free = np.linalg.solve(mixer, a.u_pred.T).T
    assert free.min() < 0.0 and free.max() > force_max  # beyond what four rotors can do
    spec = FullMpcSpec(
        horizon=6, rotor_mixer=tuple(tuple(r) for r in mixer), rotor_force_max=force_max
    )
    c = FullStateMpc(spec).solve(x0, ref, np.zeros((6, 4)), 0.03)
    assert c.ok
    forces = np.linalg.solve(mixer, c.u_pred.T).T
    assert forces.min() > -1e-7 and forces.max() < force_max + 1e-7


def test_hybrid_mpc_equals_the_network_inside_the_graph():
    """The Callback formulation converges to the answer of IPOPT with the network in the SX graph."""
    n, substeps = 3, 2  # small, so the reference's symbolic Hessian stays cheap
    layout = replace(ResidualLayout.paper(), hidden=16)
    res = _queue(layout, 2, seed=3)
    hybrid = FullStateMpc(FullMpcSpec(horizon=n, substeps=substeps, residual_rows=layout.rows))
    x0 = np.zeros(13)
    x0[0], x0[4], x0[6] = 2.0, 0.3, 1.0
    x_ref = _hover_ref(n, (2.0, 0.1, 0.0))
    x_ref[:, 4] = 0.8
    sol = hybrid.solve(x0, x_ref, np.zeros((n, 4)), 0.03, res)
    assert sol.ok

    # Reference: the same problem with the network written into CasADi.
    be = casadi_backend()
    layers = [(ca.DM(l1), ca.DM(b1), ca.DM(l2), ca.DM(b2)) for l1, b1, l2, b2 in _weights(res)]

    def f(y, uu):
        z = ca.vertcat(y, uu)
        out = rigid_body_rhs(y, uu, 0.03, INERTIA, G, be)
        for w1, b1, w2, b2 in layers:
            out = out + ca.mtimes(w2, ca.tanh(ca.mtimes(w1, z) + b1)) + b2
        return out

    w = ca.SX.sym("w", 17 * n)
    h = 0.05 / substeps
    x, cost, g = ca.DM(x0), 0, []
    for k in range(n):
        uk, xn = w[17 * k : 17 * k + 4], w[17 * k + 4 : 17 * k + 17]
        y = x
        for _ in range(substeps):
            y = rk4_step(f, y, uk, h)
        g.append(xn - y)
        e = xn - x_ref[k]
        cost = cost + ca.dot(e, e) + ca.dot(uk, uk)
        x = xn
    solver = ca.nlpsol("ref", "ipopt", {"x": w, "f": cost, "g": ca.vertcat(*g)}, {"print_time": False, "ipopt": {"print_level": 0, "sb": "yes"}})
    lbx = np.full(17 * n, -np.inf)
    ubx = np.full(17 * n, np.inf)
    lbx[0::17], ubx[0::17] = 0.0, 0.575
    ref = np.asarray(solver(x0=0, lbx=lbx, ubx=ubx, lbg=0, ubg=0)["x"]).ravel().reshape(n, 17)
    assert solver.stats()["success"]
    np.testing.assert_allclose(sol.u_pred, ref[:, :4], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(sol.x_pred[1:], ref[:, 4:], atol=1e-7)


def _weights(res: NumpyResidual) -> list[tuple[np.ndarray, ...]]:
    """The folded queue as one equivalent network per block: (W1 (h, 17), b1, W2 (13, h), b2)."""
    w1 = np.zeros((res._w1.shape[0], 17))
    w1[:, res._inputs] = res._w1
    return [(w1, res._b1, res._w2, res._b2)]


def test_residual_rows_are_checked():
    nominal = FullStateMpc(FullMpcSpec(horizon=3))
    res = _queue(ResidualLayout.default(), 1, seed=0)
    x0 = np.zeros(13)
    x0[6] = 1.0
    with pytest.raises(ValueError, match="without residual rows"):
        nominal.solve(x0, _hover_ref(3), np.zeros((3, 4)), 0.03, res)
    paper_rows = FullStateMpc(FullMpcSpec(horizon=3, residual_rows=tuple(range(13))))
    with pytest.raises(ValueError, match="rows"):
        paper_rows.solve(x0, _hover_ref(3), np.zeros((3, 4)), 0.03, res)
    with pytest.raises(ValueError):
        FullMpcSpec(q=(1.0,) * 12)
