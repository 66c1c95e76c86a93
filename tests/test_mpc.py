"""Translational MPC: agreement RTI vs IPOPT, physics sanity, residual parameters, failures, codegen cache."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.flight import mpc as mpc_module
from cfknode.flight import mpc_codegen, mpc_problem
from cfknode.flight.mpc import (
    ResidualLinearisation,
    TranslationalMpc,
    acceleration_bounds,
)
from cfknode.flight.trajectory import circle_samples
from cfknode.models.quadrotor import rk4_step


@dataclass(frozen=True)
class Ref:
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray


def _cfg(**overrides: object):
    # The MPC's own problem (the per-axis box); the thrust cone of the fast layer is tested in test_adaptation.py.
    base = {"controller.codegen": False, "controller.adaptation": "none"}
    base.update({f"controller.{k}": v for k, v in overrides.items()})
    return load_config(overrides=base)


@pytest.fixture(scope="module")
def cfg():
    return _cfg()


@pytest.fixture(scope="module")
def rti(cfg):
    return TranslationalMpc(cfg.controller, cfg.vehicle)


@pytest.fixture(scope="module")
def ipopt():
    c = _cfg(solver="ipopt")
    return TranslationalMpc(c.controller, c.vehicle)


def _hover_ref(n: int, height: float = 1.0) -> Ref:
    return Ref(np.tile([0.0, 0.0, height], (n + 1, 1)), np.zeros((n + 1, 3)), np.zeros((n + 1, 3)))


def _random_residual(rng: np.random.Generator, n: int, scale: float = 1.0) -> ResidualLinearisation:
    return ResidualLinearisation(
        scale * rng.normal(0.0, 0.5, (n, 3)),
        scale * rng.normal(0.0, 0.2, (n, 3, 6)),
        scale * rng.normal(0.0, 0.1, (n, 3, 3)),
    )


def _rollout(x0: np.ndarray, u: np.ndarray, res: ResidualLinearisation, h: float) -> np.ndarray:
    """numpy RK4 of p' = v, v' = u + c_k + Jx_k x + Ju_k u, stage by stage."""
    xs = [x0]
    for k in range(u.shape[0]):

        def f(x: np.ndarray, uk: np.ndarray, k: int = k) -> np.ndarray:
            return np.concatenate((x[3:], uk + res.c[k] + res.jx[k] @ x + res.ju[k] @ uk))

        xs.append(rk4_step(f, xs[-1], u[k], h))
    return np.array(xs)


def test_rti_and_ipopt_agree_on_random_problems(rti, ipopt):
    rng = np.random.default_rng(7)
    n, dt = rti.horizon, rti.dt
    for case in range(6):
        t = dt * np.arange(n + 1) + rng.uniform(0, 10)
        ref = circle_samples(t, rng.uniform(0.3, 1.5), rng.uniform(0.2, 1.2), rng.uniform(0.5, 2.0))
        x0 = np.concatenate((ref.p[0] + rng.normal(0, 0.2, 3), ref.v[0] + rng.normal(0, 0.3, 3)))
        if case == 5:
            x0[:3] += (2.0, -1.5, 1.0)  # bounds active: both must find the same constrained optimum
        residual = _random_residual(rng, n, scale=0.5) if case % 2 else None
        a = rti.solve(x0, ref, residual)
        b = ipopt.solve(x0, ref, residual)
        assert a.ok and b.ok, (a.status, b.status)
        np.testing.assert_allclose(a.acc, b.acc, atol=1e-4)
        np.testing.assert_allclose(a.u_pred, b.u_pred, atol=1e-4)
        np.testing.assert_allclose(a.x_pred, b.x_pred, atol=1e-5)


def test_osqp_matches_qrqp(rti):
    c = _cfg(qp_solver="osqp")
    osqp = TranslationalMpc(c.controller, c.vehicle)
    ref = _hover_ref(rti.horizon)
    for x0 in (np.array([0.3, -0.2, 0.8, 0.1, 0.0, -0.2]), np.array([3.0, 0.0, -1.0, 0.0, 0.0, 0.0])):
        a, b = rti.solve(x0, ref), osqp.solve(x0, ref)
        assert a.ok and b.ok
        np.testing.assert_allclose(a.acc, b.acc, atol=1e-4)


def test_hover_reference_at_hover_gives_zero_acceleration(rti):
    sol = rti.solve(np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0]), _hover_ref(rti.horizon))
    assert sol.ok and sol.status == "ok"
    np.testing.assert_allclose(sol.acc, 0.0, atol=1e-9)
    np.testing.assert_allclose(sol.u_pred, 0.0, atol=1e-9)
    np.testing.assert_allclose(sol.x_pred, np.tile([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], (rti.horizon + 1, 1)), atol=1e-9)


def test_the_vertical_thrust_margin_is_configurable(cfg):
    import dataclasses

    full = acceleration_bounds(cfg.controller, cfg.vehicle).upper[2]
    margin = acceleration_bounds(dataclasses.replace(cfg.controller, max_thrust_fraction=0.9), cfg.vehicle).upper[2]
    assert full - margin == pytest.approx(0.1 * cfg.vehicle.max_thrust / cfg.vehicle.mass)
    heavy = dataclasses.replace(cfg.vehicle, mass=cfg.vehicle.max_thrust / cfg.vehicle.gravity * 1.2)
    with pytest.raises(ValueError, match="cannot hover"):
        acceleration_bounds(cfg.controller, heavy)


def test_position_offset_accelerates_toward_reference(rti):
    offset = np.array([0.2, -0.1, -0.3])
    x0 = np.concatenate(([0.0, 0.0, 1.0] + offset, np.zeros(3)))
    sol = rti.solve(x0, _hover_ref(rti.horizon))
    assert sol.ok
    assert np.all(np.sign(sol.acc) == -np.sign(offset))
    # The predicted path ends closer to the reference than it starts.
    assert np.linalg.norm(sol.x_pred[-1, :3] - [0.0, 0.0, 1.0]) < 0.2 * np.linalg.norm(offset)


def test_bounds_respected_under_large_error(rti, cfg):
    bounds = acceleration_bounds(cfg.controller, cfg.vehicle)
    g = cfg.vehicle.gravity
    assert bounds.lower[2] == pytest.approx(-(1 - cfg.controller.min_thrust_fraction) * g)
    assert bounds.upper[2] == pytest.approx(cfg.controller.max_thrust_fraction * cfg.vehicle.max_thrust / cfg.vehicle.mass - g)
    assert bounds.upper[0] == pytest.approx(g * np.tan(np.radians(cfg.controller.max_tilt_deg)))
    ref = _hover_ref(rti.horizon)
    for x0 in (np.array([5.0, -5.0, -3.0, 0.0, 0.0, 0.0]), np.array([-5.0, 5.0, 6.0, 2.0, -2.0, 3.0])):
        sol = rti.solve(x0, ref)
        assert sol.ok
        assert np.all(sol.u_pred >= bounds.lower - 1e-9) and np.all(sol.u_pred <= bounds.upper + 1e-9)
        # Far away, the first command saturates on every axis, toward the reference.
        expected = np.where(x0[:3] > ref.p[0], bounds.lower, bounds.upper)
        np.testing.assert_allclose(sol.acc, expected, atol=1e-6)


def test_stale_warm_start_never_gives_a_wrong_answer(rti, ipopt):
    """Saturated solve, then an unrelated easy one: qrqp's stale active set must not leak through."""
    ref = _hover_ref(rti.horizon)
    rng = np.random.default_rng(11)
    for _ in range(5):
        far = np.concatenate((rng.uniform(-4, 4, 3), rng.uniform(-3, 3, 3)))
        assert rti.solve(far, ref).ok
        near = np.concatenate(([0.0, 0.0, 1.0] + rng.normal(0, 0.05, 3), rng.normal(0, 0.05, 3)))
        a, b = rti.solve(near, ref), ipopt.solve(near, ref)
        assert a.ok and b.ok
        np.testing.assert_allclose(a.u_pred, b.u_pred, atol=1e-4)


def test_closed_loop_double_integrator_tracks_circle(rti):
    n, dt = rti.horizon, rti.dt
    control_dt, substeps = 0.01, 5  # MPC at 100 Hz, plant RK4 at 500 Hz with the command held
    radius, speed, height = 0.5, 0.4, 1.0
    x = np.array([radius, 0.0, 0.0, 0.0, 0.0, 0.0])  # on the ground below the circle start, at rest
    plant = lambda xs, us: np.concatenate((xs[3:], us))  # noqa: E731
    errors = []
    for i in range(600):
        t = i * control_dt
        sol = rti.solve(x, circle_samples(t + dt * np.arange(n + 1), radius, speed, height))
        assert sol.ok
        for _ in range(substeps):
            x = rk4_step(plant, x, sol.acc, control_dt / substeps)
        errors.append(np.linalg.norm(x[:3] - circle_samples(np.array([t + control_dt]), radius, speed, height).p[0]))
    errors = np.array(errors)
    assert errors[0] > 0.5  # it really started 1 m away
    assert errors[-200:].max() < 5e-3


def test_constant_residual_shifts_steady_state_command(rti):
    n = rti.horizon
    ref = _hover_ref(n)
    residual = ResidualLinearisation(np.tile([0.0, 0.0, -1.0], (n, 1)), np.zeros((n, 3, 6)), np.zeros((n, 3, 3)))
    function = rti.function
    plant = lambda xs, us: np.concatenate((xs[3:], us + residual.c[0]))  # noqa: E731
    x = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    for _ in range(300):
        sol = rti.solve(x, ref, residual)
        x = rk4_step(plant, x, sol.acc, 0.01)
    assert sol.ok
    np.testing.assert_allclose(sol.acc, [0.0, 0.0, 1.0], atol=1e-4)
    assert abs(x[2] - 1.0) < 5e-3  # only the small offset the input weight trades for
    # Back to nominal: the residual block is zeroed, the hover command is zero again.
    nominal = rti.solve(np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0]), ref)
    np.testing.assert_allclose(nominal.acc, 0.0, atol=1e-9)
    assert rti.function is function  # a new model is a parameter write, never a rebuild


def test_residual_parameters_enter_each_stage_as_written(rti):
    """The predicted trajectory is the numpy RK4 rollout of the affine residual model: layout check."""
    rng = np.random.default_rng(3)
    n, dt = rti.horizon, rti.dt
    residual = _random_residual(rng, n)
    ref = circle_samples(dt * np.arange(n + 1), 0.5, 0.4, 1.0)
    x0 = np.array([0.45, 0.05, 0.9, 0.0, 0.3, 0.1])
    first = rti.function
    sol = rti.solve(x0, ref, residual)
    assert sol.ok
    np.testing.assert_allclose(sol.x_pred, _rollout(x0, sol.u_pred, residual, dt), atol=1e-9)
    other = _random_residual(rng, n)
    sol2 = rti.solve(x0, ref, other)
    np.testing.assert_allclose(sol2.x_pred, _rollout(x0, sol2.u_pred, other, dt), atol=1e-9)
    assert not np.allclose(sol.acc, sol2.acc)
    assert rti.function is first


def test_linearisation_about_a_point():
    rng = np.random.default_rng(1)
    n = 4
    value, jx, ju = rng.normal(size=(n, 3)), rng.normal(size=(n, 3, 6)), rng.normal(size=(n, 3, 3))
    x_bar, u_bar = rng.normal(size=(n, 6)), rng.normal(size=(n, 3))
    lin = ResidualLinearisation.about(value, jx, ju, x_bar, u_bar)
    at_point = lin.c + np.einsum("kij,kj->ki", lin.jx, x_bar) + np.einsum("kij,kj->ki", lin.ju, u_bar)
    np.testing.assert_allclose(at_point, value, atol=1e-12)


@pytest.mark.parametrize("which", ["x0", "ref", "residual"])
def test_nonfinite_inputs_give_not_ok(rti, ipopt, which):
    n = rti.horizon
    for mpc in (rti, ipopt):
        x0 = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
        ref = _hover_ref(n)
        residual = ResidualLinearisation.zeros(n)
        if which == "x0":
            x0[4] = np.nan
        elif which == "ref":
            ref.p[3, 1] = np.inf
        else:
            residual.jx[2, 1, 3] = np.nan
        sol = mpc.solve(x0, ref, residual)
        assert not sol.ok and sol.status == "nonfinite_input"
        assert np.all(np.isfinite(sol.acc))
        assert sol.x_pred.shape == (n + 1, 6) and sol.u_pred.shape == (n, 3)
        # The next good tick solves normally.
        assert mpc.solve(np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0]), _hover_ref(n)).ok


def _starved_options(original, starve_osqp: bool):
    """QP options with an iteration limit too small to converge (qrqp always, OSQP optionally)."""

    def options(qp: str) -> dict:
        opts = original(qp)
        if qp == "qrqp":
            return {**opts, "max_iter": 1}
        if starve_osqp:
            return {**opts, "osqp": {**opts["osqp"], "max_iter": 1}}
        return opts

    return options


def test_failed_qp_is_rescued_by_osqp(monkeypatch, ipopt):
    """qrqp stopping early is caught by the KKT check; the OSQP rescue gives the right answer."""
    monkeypatch.setattr(mpc_problem, "_qp_options", _starved_options(mpc_problem._qp_options, starve_osqp=False))
    c = _cfg()
    mpc = TranslationalMpc(c.controller, c.vehicle)
    x0 = np.array([3.0, 0.0, -2.0, 0.0, 0.0, 0.0])
    sol = mpc.solve(x0, _hover_ref(mpc.horizon))
    assert sol.ok and mpc.rescues == 1
    np.testing.assert_allclose(sol.u_pred, ipopt.solve(x0, _hover_ref(mpc.horizon)).u_pred, atol=1e-4)


def test_failed_qp_gives_not_ok(monkeypatch):
    """When the rescue fails too, the failure is reported, never raised, and the next tick recovers."""
    monkeypatch.setattr(mpc_problem, "_qp_options", _starved_options(mpc_problem._qp_options, starve_osqp=True))
    c = _cfg(horizon=5)
    mpc = TranslationalMpc(c.controller, c.vehicle)
    sol = mpc.solve(np.array([3.0, 0.0, -2.0, 0.0, 0.0, 0.0]), _hover_ref(5))
    assert not sol.ok and sol.status == "solver_failed"
    np.testing.assert_array_equal(sol.acc, 0.0)
    assert np.all(np.isnan(sol.x_pred))
    assert mpc.solve(np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0]), _hover_ref(5)).ok


def test_codegen_compiles_once_and_is_reused(tmp_path):
    c = load_config(overrides={"controller.codegen": True, "controller.horizon": 4,  # small N: fast gcc
                               "controller.adaptation": "none"})
    first = TranslationalMpc(c.controller, c.vehicle, cache_dir=tmp_path)
    assert first.backend == "rti-qrqp-codegen"
    assert first.compiled is not None and first.compiled.compiled_now
    second = TranslationalMpc(c.controller, c.vehicle, cache_dir=tmp_path)
    assert second.compiled is not None and not second.compiled.compiled_now
    assert second.compiled.library == first.compiled.library
    assert [p.name for p in tmp_path.iterdir()] == [first.compiled.library.name]  # no temp files left behind
    vm = TranslationalMpc(_cfg(horizon=4).controller, c.vehicle)
    rng = np.random.default_rng(0)
    residual = _random_residual(rng, 4, scale=0.5)
    ref = circle_samples(0.05 * np.arange(5), 0.5, 0.4, 1.0)
    x0 = np.array([0.6, -0.1, 0.7, 0.0, 0.2, 0.0])
    a, b = second.solve(x0, ref, residual), vm.solve(x0, ref, residual)
    assert a.ok and b.ok
    np.testing.assert_allclose(a.acc, b.acc, atol=1e-9)
    np.testing.assert_allclose(a.x_pred, b.x_pred, atol=1e-9)


def test_codegen_failure_falls_back_to_vm(monkeypatch, tmp_path):
    monkeypatch.setattr(mpc_codegen.shutil, "which", lambda name: None)
    monkeypatch.setattr(mpc_module, "_warned_compile", False)
    c = load_config(overrides={"controller.codegen": True, "controller.horizon": 4})
    with pytest.warns(RuntimeWarning, match="using the CasADi VM"):
        mpc = TranslationalMpc(c.controller, c.vehicle, cache_dir=tmp_path)
    assert mpc.backend == "rti-qrqp-vm" and mpc.compiled is None
    assert mpc.solve(np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0]), _hover_ref(4)).ok
