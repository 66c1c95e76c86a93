"""The learner's commands as they act: through the motors' and the attitude loop's lags (flight/learning/command_lag.py).

Measured against the command as sent, the motors' lag is a force on the command's rate; on a vertical oscillation
that rate follows the velocity, and it hid the thrust lost with climb rate from every network."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.app.learning import learner_settings
from cfknode.flight.learning.command_lag import CommandLag, lagged_commands
from cfknode.flight.learning.windows import WindowRecorder

RATE = 400.0


def test_each_axis_follows_its_own_first_order_lag():
    lag = CommandLag((0.05, 0.015), max_gap=3.0 / RATE)
    step = np.array([1.0, -2.0, 3.0])
    lag(0.0, np.zeros(3))
    for k in range(1, 7):  # 15 ms: one vertical time constant
        out = lag(k / RATE, step)
    assert out[2] == pytest.approx(3.0 * (1.0 - math.exp(-1.0)), rel=1e-9)
    assert out[0] == pytest.approx(1.0 * (1.0 - math.exp(-0.015 / 0.05)), rel=1e-9)
    assert out[1] == pytest.approx(-2.0 * (1.0 - math.exp(-0.015 / 0.05)), rel=1e-9)


def test_a_zero_lag_passes_the_command_and_a_gap_restarts_the_lag():
    lag = CommandLag((0.0, 0.015), max_gap=3.0 / RATE)
    lag(0.0, np.zeros(3))
    out = lag(1.0 / RATE, np.array([2.0, 2.0, 2.0]))
    assert out[0] == out[1] == 2.0 and 0.0 < out[2] < 2.0
    # A gap (flown blind, or on the ground) holds no memory of what the motors did before it.
    assert np.array_equal(lag(1.0, np.array([5.0, 5.0, 5.0])), [5.0, 5.0, 5.0])


def _tick(t: float, acc: np.ndarray, z: float = 1.0, v: np.ndarray | None = None):
    est = SimpleNamespace(p=np.array([0.0, 0.0, z]), v=np.zeros(3) if v is None else v, q=np.array([1.0, 0.0, 0.0, 0.0]))
    return SimpleNamespace(t=t, est=est, acc=acc, source="mpc", model_version=0, compute_s=0.0, layer=None)


def test_the_recorder_records_the_lagged_command_and_lags_the_ticks_it_does_not_record():
    lagged = WindowRecorder(0.5, RATE, ground_z=0.0, command_lag_s=(0.0, 0.015))
    sent = WindowRecorder(0.5, RATE, ground_z=0.0)
    step = np.array([0.0, 0.0, 4.0])
    # The first 20 ticks are below the floor margin: not recorded, but the motors lagged them all the same.
    for k in range(40):
        tick = _tick(k / RATE, step if k >= 10 else np.zeros(3), z=0.05 if k < 20 else 1.0)
        lagged.add(tick)
        sent.add(tick)
    assert np.array_equal(sent.last_u, step)
    assert lagged.last_u[2] == pytest.approx(4.0 * (1.0 - math.exp(-30 / (RATE * 0.015))), rel=1e-9)
    _, _, u = lagged.fresh(0.0)
    assert u[0, 2] == pytest.approx(4.0 * (1.0 - math.exp(-11 / (RATE * 0.015))), rel=1e-9)  # the first recorded tick


def test_against_the_lagged_command_a_vertical_oscillation_shows_the_thrust_lost_with_climb_rate():
    """A vehicle whose motors lag 15 ms and which loses 0.4 m/s^2 of thrust per m/s of climb, commanded along a
    0.65 Hz, 0.25 m oscillation: the command's rate follows the velocity, so against the command as sent the
    target's slope on v_z is mostly the motors' lag; against the lagged command it is the inflow's."""
    tau, k_in, w, dt = 0.015, -0.4, 2.0 * math.pi * 0.65, 1.0 / RATE
    recorders = {lag: WindowRecorder(10.0, RATE, ground_z=0.0, command_lag_s=(0.0, lag)) for lag in (0.0, tau)}
    acting, v, rows = 0.0, 0.0, []
    for k in range(int(4.0 * RATE)):
        t = k * dt
        u = -0.25 * w * w * math.sin(w * t) + k_in * 0.25 * w * math.cos(w * t)  # the command a tracker would send
        tick = _tick(t, np.array([0.0, 0.0, u]), v=np.array([0.0, 0.0, v]))
        for rec in recorders.values():
            rec.add(tick)
        acting += (1.0 - math.exp(-dt / tau)) * (u - acting)
        a = acting + k_in * v
        rows.append((v, a))
        v += a * dt
    vz, a = np.array(rows).T
    slopes = {}
    for lag, rec in recorders.items():
        _, _, u = rec.fresh(-1.0)
        target = a[-u.shape[0]:] - u[:, 2]
        slopes[lag] = np.polyfit(vz[-u.shape[0]:], target, 1)[0]
    assert slopes[tau] == pytest.approx(k_in, abs=0.02)
    assert slopes[0.0] > k_in + 0.15  # the motors' lag (tau w^2 = +0.25) hides most of it


def test_beside_the_layer_the_motors_lag_reaches_the_learner_and_without_it_the_command_is_as_sent():
    cfg = load_config()
    assert learner_settings(cfg, lockstep=True).command_lag_s == (0.0, cfg.vehicle.motor_time_constant)
    alone = load_config(overrides={"controller.adaptation": "none"})
    assert learner_settings(alone, lockstep=True).command_lag_s == (0.0, 0.0)  # the paper learner's targets
    lagged = load_config(overrides={"controller.adaptation": "none", "online.command_lag_s": [0.0, 0.015]})
    assert learner_settings(lagged, lockstep=True).command_lag_s == (0.0, 0.015)
    sent = load_config(overrides={"online.layer_command_lag_s": [0.0, 0.0]})
    assert learner_settings(sent, lockstep=True).command_lag_s == (0.0, 0.0)


def test_offline_segments_are_lagged_as_the_recorder_lags_them_and_the_neighbour_columns_are_kept():
    rng = np.random.default_rng(0)
    t = np.arange(200) / RATE
    u = np.concatenate((rng.normal(size=(200, 3)), np.tile([0.1, 0.0, 0.3], (200, 1))), axis=1)  # + a neighbour
    out = lagged_commands(t, u, (0.02, 0.015))
    rec = WindowRecorder(10.0, RATE, ground_z=0.0, command_lag_s=(0.02, 0.015))
    for i in range(200):
        rec.add(_tick(float(t[i]), u[i, :3]))
    _, _, recorded = rec.fresh(-1.0)
    assert np.array_equal(out[:, :3], recorded)
    assert np.array_equal(out[:, 3:], u[:, 3:])
    assert np.array_equal(lagged_commands(t, u, (0.0, 0.0)), u)


def test_cfknode_train_reads_its_segments_through_the_training_lag(monkeypatch):
    import argparse

    import cfknode.app.logs.training_data as training_data
    from cfknode.app.commands.data_args import read_segments
    from cfknode.models.training import Segment

    t = np.arange(100) / RATE
    u = np.zeros((100, 3))
    u[10:, 2] = 2.0  # a step the motors follow over 15 ms
    seg = Segment(t, np.zeros((100, 6)), u, "flight.mcap")
    monkeypatch.setattr(training_data, "segments_from_logs", lambda paths, on_damage: [seg])
    args = argparse.Namespace(log=["flight.mcap"], data=[], columns=None, thrust_coefficient=None, align="auto",
                              every=1, robot=None)
    plain, _ = read_segments(args, load_config())
    assert np.array_equal(plain[0].u, u)
    lagged, _ = read_segments(args, load_config(overrides={"training.command_lag_s": [0.0, 0.015]}))
    assert np.array_equal(lagged[0].u, lagged_commands(t, u, (0.0, 0.015)))
    assert 0.0 < lagged[0].u[11, 2] < 1.0 and lagged[0].u[-1, 2] == pytest.approx(2.0, abs=1e-6)
