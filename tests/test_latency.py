"""Prediction across the command path (estimator.command_delay)."""

from __future__ import annotations

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
