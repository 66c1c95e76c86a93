"""Prediction across the command path (estimator.command_delay)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cfknode.app.config import ConfigError, load_config
from cfknode.flight.estimator import StateEstimate, VelocityEstimator
from cfknode.flight.latency import CommandDelayPredictor
from cfknode.app.mission import run_flight


def _est(t: float, p=(0.0, 0.0, 1.0), v=(0.5, 0.0, 0.0)) -> StateEstimate:
    return StateEstimate(t=t, p=np.array(p, float), v=np.array(v, float), q=np.array([1.0, 0, 0, 0]), yaw=0.0)


def test_no_delay_returns_the_estimate_itself():
    pred = CommandDelayPredictor(0.0)
    pred.note(0.0, np.ones(3))
    est = _est(0.1)
    assert pred.ahead(est) is est


def test_constant_command_moves_the_state_by_the_kinematics():
    d, a = 0.03, np.array([1.0, -2.0, 0.5])
    pred = CommandDelayPredictor(d)
    for k in range(40):  # 400 Hz ticks
        pred.note(k * 0.0025, a)
    now = 40 * 0.0025
    out = pred.ahead(_est(now))
    assert out.t == pytest.approx(now + d)
    np.testing.assert_allclose(out.p, [0.0, 0.0, 1.0] + np.array([0.5, 0, 0]) * d + 0.5 * a * d * d, atol=1e-12)
    np.testing.assert_allclose(out.v, [0.5, 0.0, 0.0] + a * d, atol=1e-12)


def test_only_the_commands_in_flight_count():
    # Commands sent before now - delay already act on the measured state; over [now, now + d]
    # the vehicle flies those sent in [now - d, now): here the old one for d/2, the new one for d/2.
    d = 0.04
    pred = CommandDelayPredictor(d)
    pred.note(0.0, np.zeros(3))
    pred.note(0.08, np.array([0.0, 0.0, 2.0]))
    out = pred.ahead(_est(0.1, v=(0.0, 0.0, 0.0)))
    # The window [0.06, 0.10): zero for 0.02 s, then 2 m/s^2 for 0.02 s.
    assert out.v[2] == pytest.approx(2.0 * 0.02)
    assert out.p[2] == pytest.approx(1.0 + 0.5 * 2.0 * 0.02**2)


def test_estimator_owns_the_predictor_and_reset_clears_it():
    cfg = load_config(overrides={"estimator.command_delay": 0.02})
    est = VelocityEstimator(cfg.estimator)
    assert est.command_path.delay == 0.02
    est.command_path.note(0.0, np.ones(3))
    est.reset()
    e = _est(0.01)
    assert est.command_path.ahead(e) is e
    with pytest.raises(ConfigError, match="command_delay"):
        load_config(overrides={"estimator.command_delay": -0.01})


def test_a_flight_with_command_delay_compensation_tracks(tmp_path):
    short = {"trajectory.duration": 3.0, "trajectory.takeoff_duration": 1.5, "trajectory.settle_duration": 0.3,
             "trajectory.land_duration": 1.5, "trajectory.ramp_duration": 1.0, "log.dir": str(tmp_path),
             "estimator.command_delay": 0.02, "estimator.latency": 0.004}
    res = run_flight(load_config(overrides=short), name_hint="delay")
    assert res.outcome.message.startswith("flight complete")
    assert res.summary.mse < 5e-4


def test_the_layer_and_the_observers_see_the_measured_state_while_the_mpc_plans_ahead():
    # With estimator.command_delay the MPC plans from the state predicted ahead (flight/latency.py); the fast
    # layer and the online learner compare the vehicle with what it did, so they must get the measured one.
    # (Fed the prediction, the layer read the prediction's error as a disturbance: on a fast loop its offset
    # swung +-0.8 m/s^2 and it flew 3.2x nominal MPC's error, docs/results.md.)
    import cfknode

    cfg = load_config(overrides={"controller.adaptation": "dob"})
    ctrl = cfknode.Controller(cfg.controller, cfg.vehicle, ground_z=0.0)
    seen, ticks = [], []
    before = ctrl.adaptation.before_solve

    def spy(now, est, *args):
        seen.append(est)
        return before(now, est, *args)

    ctrl.adaptation.before_solve = spy

    class Observer:
        def on_tick(self, tick):
            ticks.append(tick)

    ctrl.observers.append(Observer())
    measured = _est(0.0, v=(0.5, 0.0, 0.0))
    ahead = _est(0.0, p=(0.075, 0.0, 1.0), v=(0.8, 0.0, 0.0))
    hover = cfknode.RefSamples(ctrl.preview_times(0.0), np.tile([0.0, 0.0, 1.0], (cfg.controller.horizon + 1, 1)),
                               np.zeros((cfg.controller.horizon + 1, 3)), np.zeros((cfg.controller.horizon + 1, 3)),
                               np.zeros(cfg.controller.horizon + 1))
    planned = ctrl.step(0.0, ahead, hover, observed=measured)
    ctrl.publish()
    assert seen == [measured] and ticks[0].est is measured
    # The plan is the ahead state's: the same step without a prediction plans differently.
    plain = cfknode.Controller(cfg.controller, cfg.vehicle, ground_z=0.0).step(0.0, measured, hover)
    assert not np.allclose(planned.acc, plain.acc)
    # Without ``observed`` the state is both (no delay: the flight is unchanged).
    ctrl.step(0.0025, measured, hover)
    assert seen[-1] is measured


def test_held_increments_integrate_the_held_commands_exactly():
    from cfknode.flight.latency import held_increments

    times = np.array([0.0, 0.1, 0.2])
    accs = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, -1.0]])
    # Over [0.05, 0.25]: 1 for 0.05 s, 2 for 0.1 s, -1 for 0.05 s (the last command held on).
    dv, dp = held_increments(times, accs, 0.05, 0.25)
    np.testing.assert_allclose(dv, [0.05, 0.2, -0.05], atol=1e-15)
    # Position from b - s weights: the first piece's midpoint is 0.175 s before b, the second's 0.1, the third's 0.025.
    np.testing.assert_allclose(dp, [0.05 * 0.175, 0.2 * 0.1, -0.05 * 0.025], atol=1e-15)
    # Before the first command nothing is known: it adds nothing.
    dv0, dp0 = held_increments(times, accs, -1.0, 0.0)
    assert not dv0.any() and not dp0.any()


def test_the_vertical_axis_is_predicted_over_its_own_delay():
    d, dz, a = 0.15, 0.02, np.array([1.0, -1.0, 2.0])
    pred = CommandDelayPredictor(d, delay_z=dz)
    for k in range(100):
        pred.note(k * 0.0025, a)
    now = 100 * 0.0025
    out = pred.ahead(_est(now, v=(0.0, 0.0, 0.0)))
    assert out.t == pytest.approx(now + d)
    np.testing.assert_allclose(out.v, [d, -d, 2.0 * dz], atol=1e-12)
    np.testing.assert_allclose(out.p, [0.5 * d * d, -0.5 * d * d, 1.0 + dz * dz], atol=1e-12)


def test_the_unexplained_acceleration_is_learned_and_predicted_with():
    # The vehicle flies the commands a delay late plus a constant 0.3 m/s^2 (a drag) the commands do not
    # explain; once learned the prediction is exact, where the commands alone miss 0.3 m/s^2 times the delay.
    d, dt, extra = 0.1, 0.0025, np.array([0.3, -0.3, 0.0])
    a = np.array([1.0, 0.5, 0.0])
    pred = CommandDelayPredictor(d, residual_tau=0.02)
    plain = CommandDelayPredictor(d)
    v = np.zeros(3)
    for k in range(400):
        t = k * dt
        est = _est(t, p=(0.0, 0.0, 1.0), v=v)
        out, out_plain = pred.ahead(est), plain.ahead(est)
        pred.note(t, a)
        plain.note(t, a)
        flown = a if t - d >= 0.0 else np.zeros(3)  # the commands act a delay late
        v = v + dt * (flown + extra)
    np.testing.assert_allclose(pred.residual, extra, atol=1e-9)
    np.testing.assert_allclose(out.v - est.v, (a + extra) * d, atol=1e-9)
    np.testing.assert_allclose(out_plain.v - est.v, a * d, atol=1e-12)
    pred.reset()
    assert not pred.residual.any()


def test_lag_increments_match_the_first_order_lag_exactly():
    from cfknode.flight.latency import lag_increments_xy

    tau, h = 0.17, 0.1
    a0, u = np.array([0.5, 0.0]), np.array([1.5, -1.0])
    dvx, dvy, dpx, dpy = lag_increments_xy(*a0, *u, tau, h)
    dv, dp = np.array([dvx, dvy]), np.array([dpx, dpy])
    # a(s) = u + (a0 - u) exp(-s / tau): integrated once and twice in closed form.
    e = math.exp(-h / tau)
    np.testing.assert_allclose(dv, u * h + (a0 - u) * tau * (1.0 - e), atol=1e-15)
    np.testing.assert_allclose(dp, u * h * h / 2 + (a0 - u) * (tau * h - tau * tau * (1.0 - e)), atol=1e-15)
    # A settled lag flies the command: the plain kinematics.
    dvx, dvy, dpx, dpy = lag_increments_xy(*u, *u, tau, h)
    np.testing.assert_allclose([dvx, dvy], u * h, atol=1e-15)
    np.testing.assert_allclose([dpx, dpy], 0.5 * u * h * h, atol=1e-15)


def test_the_lag_s_float_twin_is_the_array_function_to_the_bit():
    # The floats do numpy's element-wise arithmetic in its order: the predictor's flights stayed the same to the bit.
    from cfknode.flight.latency import lag_increments_xy

    rng = np.random.default_rng(5)
    for _ in range(200):
        a0, u = rng.normal(0.0, 2.0, 3), rng.normal(0.0, 2.0, 3)
        tau, h = float(rng.uniform(0.02, 0.4)), float(rng.uniform(0.0, 0.2))
        k = -math.expm1(-h / tau)
        dv = u * h + (a0 - u) * (tau * k)
        dp = u * (0.5 * h * h) + (a0 - u) * (tau * (h - tau * k))
        assert lag_increments_xy(a0[0], a0[1], u[0], u[1], tau, h) == (dv[0], dv[1], dp[0], dp[1])


def test_with_a_lag_the_horizontal_prediction_relaxes_toward_the_newest_command():
    # A step to 1 m/s^2 on x at t = 0.1 s, predicted at 0.2 s over 0.1 s: the acting acceleration has reached
    # 1 - exp(-0.1 / tau) and keeps relaxing; z is a held command over its own 20 ms.
    from cfknode.flight.latency import lag_increments_xy

    tau, d, dz = 0.17, 0.1, 0.02
    pred = CommandDelayPredictor(d, delay_z=dz, lag=tau)
    for k in range(40):
        t = k * 0.005
        pred.note(t, np.array([1.0 if t >= 0.1 else 0.0, 0.0, 2.0]))
    out = pred.ahead(_est(0.2, v=(0.0, 0.0, 0.0)))
    acting = np.array([-math.expm1(-(0.195 - 0.1) / tau), 0.0, 0.0])  # the last note (0.195 s) held to 0.2 s
    acting = np.array([1.0, 0.0, 0.0]) + (acting - [1.0, 0.0, 0.0]) * math.exp(-0.005 / tau)
    dvx, dvy, dpx, dpy = lag_increments_xy(acting[0], acting[1], 1.0, 0.0, tau, d)
    np.testing.assert_allclose(out.v[:2], [dvx, dvy], atol=1e-12)
    np.testing.assert_allclose(out.p[:2], [dpx, dpy], atol=1e-12)
    assert out.v[2] == pytest.approx(2.0 * dz) and out.p[2] == pytest.approx(1.0 + dz * dz)


def test_vertical_delay_and_residual_settings_are_checked():
    cfg = load_config(overrides={"estimator.command_delay": 0.1, "estimator.command_delay_z": 0.02,
                                 "estimator.command_residual_tau": 0.05})
    path = VelocityEstimator(cfg.estimator).command_path
    assert (path.delay, path.delay_z, path.residual_tau) == (0.1, 0.02, 0.05)
    assert VelocityEstimator(load_config().estimator).command_path.active is False
    for key in ("estimator.command_delay_z", "estimator.command_residual_tau", "estimator.command_lag"):
        with pytest.raises(ConfigError, match=key.split(".")[1]):
            load_config(overrides={key: -0.01})
    with pytest.raises(ValueError):
        CommandDelayPredictor(0.1, delay_z=-0.01)
    with pytest.raises(ValueError):
        CommandDelayPredictor(0.1, lag=-0.1)


def test_the_compensation_tracks_a_fast_small_loop(tmp_path):
    # circle r=0.3 v=1.5 of the learning bench, nominal MPC, 3 s of pattern, seed 0: the attitude loop's lag
    # dominates. Uncompensated the MSE is 0.0337 m^2; with the lag model below 0.00168 (docs/history.md).
    from cfknode.app.bench.learning_cells import CELLS

    cell = next(c for c in CELLS if c.name == "circle r=0.3 v=1.5")
    overrides = cell.config("nominal", 0, str(tmp_path), 3.0)
    overrides.update({"estimator.command_delay": 0.10, "estimator.command_lag": 0.17,
                      "estimator.command_delay_z": 0.0, "estimator.command_residual_tau": 0.05})
    res = run_flight(load_config(overrides=overrides), name_hint="loop")
    assert res.outcome.message.startswith("flight complete")
    assert res.summary.mse < 0.005


def test_a_vertical_delay_of_its_own_takes_the_vertical_reference_from_there():
    from cfknode.flight.loop import _with_z

    xy = np.arange(6.0).reshape(2, 3)
    z = -np.arange(6.0).reshape(2, 3)
    np.testing.assert_array_equal(_with_z(xy, z), [[0.0, 1.0, -2.0], [3.0, 4.0, -5.0]])
    assert xy[0, 2] == 2.0  # the planned reference is a copy


class _Bump:
    """A residual model with a narrow vertical bump in x (a jet 5 cm wide), linearised exactly at its nodes."""

    width = 0.05

    def evaluate(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        x2 = np.atleast_2d(x)
        out = np.zeros((x2.shape[0], 3))
        out[:, 2] = -3.0 * np.exp(-x2[:, 0] ** 2 / (2.0 * self.width ** 2))
        return out if np.ndim(x) == 2 else out[0]

    def linearise(self, x_nodes: np.ndarray, u_nodes: np.ndarray):
        value = self.evaluate(x_nodes, u_nodes)
        jx = np.zeros((x_nodes.shape[0], 3, 6))
        jx[:, 2, 0] = -value[:, 2] * x_nodes[:, 0] / self.width ** 2
        ju = np.zeros((x_nodes.shape[0], 3, 3))
        c = value - np.einsum("kij,kj->ki", jx, x_nodes)
        return c, jx, ju


def test_the_layer_is_told_the_models_residual_where_the_vehicle_was_measured():
    # Planning from the state 0.1 s ahead, the model is linearised at the plan's nodes; for a narrow term (a
    # wake) that slope stretched back to the measured state is far off (here -2.0 m/s^2 where the model says
    # -3), and the layer read the difference as a disturbance. It is given the model's value there.
    import cfknode
    from cfknode.flight.model_slot import ModelSlot

    cfg = load_config(overrides={"controller.adaptation": "dob"})
    ctrl = cfknode.Controller(cfg.controller, cfg.vehicle, ground_z=0.0)
    ctrl.model = ModelSlot(_Bump(), version=1)
    flown = []
    after = ctrl.adaptation.after_command

    def spy(x0, shaped, thrust, residual):
        u = np.asarray(shaped.applied_acc, dtype=float)
        flown.append((x0, residual.c[0] + residual.jx[0] @ x0 + residual.ju[0] @ u))
        return after(x0, shaped, thrust, residual)

    ctrl.adaptation.after_command = spy
    n = cfg.controller.horizon + 1
    hover = cfknode.RefSamples(ctrl.preview_times(0.0), np.tile([0.0, 0.0, 1.0], (n, 1)), np.zeros((n, 3)),
                               np.zeros((n, 3)), np.zeros(n))
    measured = _est(0.0, p=(0.0, 0.0, 1.0), v=(1.0, 0.0, 0.0))
    ahead = _est(0.0, p=(0.1, 0.0, 1.0), v=(1.0, 0.0, 0.0))
    for k in range(3):  # from the second tick the model is linearised at the last plan's nodes, ahead
        ctrl.step(0.0025 * k, ahead, hover, observed=measured)
        ctrl.prepare()
    x0, told = flown[-1]
    np.testing.assert_allclose(x0, [0.0, 0.0, 1.0, 1.0, 0.0, 0.0])
    np.testing.assert_allclose(told, _Bump().evaluate(x0, np.zeros(3)), atol=1e-9)
    # The plan's own linearisation, stretched to the measured state, is far from it.
    nodes = ctrl._x_pred[:-1]
    c, jx, _ = _Bump().linearise(nodes, np.zeros((nodes.shape[0], 3)))
    assert abs((c[0] + jx[0] @ x0)[2] - told[2]) > 0.9
