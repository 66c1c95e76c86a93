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
