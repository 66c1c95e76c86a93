"""Simulated mocap: frame timing, latency, noise, dropouts, determinism, stats."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.mocap.simulated import SimulatedMocap, from_config
from cfknode.mocap.source import MocapStats, Pose, PoseSource, RateMeter
from cfknode.models.quadrotor import euler_zyx_to_quat

DT = 0.002


class FakeSim:
    """Stands in for SimCrazyflie: a 2 ms plant on a known path, reporting each step."""

    def __init__(self) -> None:
        self.t = 0.0
        self._k = 0
        self.state = self.true_state(0.0)
        self._observers = []

    @staticmethod
    def true_state(t: float) -> np.ndarray:
        s = np.zeros(13)
        s[0:3] = [0.3 * t, -0.2 * t, 1.0 + 0.1 * t]
        s[6:10] = euler_zyx_to_quat(0.1, -0.05, 0.5 * t)
        return s

    def add_step_observer(self, cb) -> None:
        self._observers.append(cb)

    def remove_step_observer(self, cb) -> None:
        self._observers.remove(cb)

    def step_to(self, t_target: float) -> None:
        while self.t < t_target - 1e-12:
            self._k += 1
            self.t = self._k * DT
            self.state = self.true_state(self.t)
            for cb in self._observers:
                cb(self.t, self.state)


def make(sim: FakeSim, **kw) -> SimulatedMocap:
    args = dict(rate_hz=100.0, position_noise=0.0, attitude_noise=0.0, latency=0.0, dropout_prob=0.0, seed=0)
    args.update(kw)
    return SimulatedMocap(sim, **args)


def rotation_angle(q1: np.ndarray, q2: np.ndarray) -> float:
    return 2.0 * float(np.arccos(min(1.0, abs(float(q1 @ q2)))))


def test_frames_at_multiples_of_the_period_with_true_state():
    sim = FakeSim()
    mocap = make(sim)
    assert isinstance(mocap, PoseSource)
    assert mocap.latest(0.0) is None
    seen = []
    for k in range(1, 31):
        sim.step_to(k * 0.01)
        pose = mocap.latest(sim.t)
        seen.append(pose.t)
        np.testing.assert_allclose(pose.position, sim.true_state(pose.t)[0:3], atol=1e-12)
        np.testing.assert_allclose(pose.quaternion, sim.true_state(pose.t)[6:10], atol=1e-12)
    np.testing.assert_allclose(seen, 0.01 * np.arange(1, 31), atol=1e-9)
    assert mocap.stats().frames == 30


def test_rate_not_dividing_the_plant_rate_takes_the_next_step():
    sim = FakeSim()
    mocap = make(sim, rate_hz=120.0)
    times = []
    for k in range(1, 121):
        sim.step_to(k / 120.0 + DT)
        times.append(mocap.latest(sim.t).t)
    times = np.unique(times)
    assert len(times) == 120
    lag = times - np.arange(1, 121) / 120.0
    assert lag.min() >= -1e-9 and lag.max() < DT + 1e-9


def test_latency_delays_visibility():
    sim = FakeSim()
    mocap = make(sim, latency=0.004)
    sim.step_to(0.05)
    assert mocap.latest(0.0139) is None
    assert mocap.latest(0.014).t == pytest.approx(0.01)
    assert mocap.latest(0.05).t == pytest.approx(0.04)
    assert mocap.latest(0.054).t == pytest.approx(0.05)
    # Asking for an earlier time never goes back to an older frame.
    assert mocap.latest(0.02).t == pytest.approx(0.05)


def test_position_and_attitude_noise_statistics():
    sim = FakeSim()
    sigma_p, sigma_q = 0.01, 0.02
    mocap = make(sim, position_noise=sigma_p, attitude_noise=sigma_q, seed=4)
    errs, angles = [], []
    for k in range(1, 3001):
        sim.step_to(k * 0.01)
        pose = mocap.latest(sim.t)
        truth = sim.true_state(pose.t)
        errs.append(pose.position - truth[0:3])
        angles.append(rotation_angle(pose.quaternion, truth[6:10]))
        assert abs(np.linalg.norm(pose.quaternion) - 1.0) < 1e-12
    errs = np.array(errs)
    np.testing.assert_allclose(errs.std(axis=0), sigma_p, rtol=0.08)
    assert np.all(np.abs(errs.mean(axis=0)) < 4 * sigma_p / np.sqrt(len(errs)))
    # A rotation vector with per-axis std s has rms angle s * sqrt(3).
    assert np.sqrt(np.mean(np.square(angles))) == pytest.approx(sigma_q * np.sqrt(3), rel=0.08)


def test_dropouts_are_counted_and_skipped():
    sim = FakeSim()
    mocap = make(sim, dropout_prob=0.3, seed=7)
    delivered = set()
    for k in range(1, 2001):
        sim.step_to(k * 0.01)
        pose = mocap.latest(sim.t)
        if pose is not None:
            delivered.add(round(pose.t, 6))
    stats = mocap.stats()
    assert stats.frames + stats.dropouts == 2000
    assert stats.dropouts / 2000 == pytest.approx(0.3, abs=0.04)
    assert len(delivered) == stats.frames
    assert stats.rate_hz == pytest.approx(70.0, abs=10.0)


def test_rate_estimate_and_stats_type():
    sim = FakeSim()
    mocap = make(sim)
    assert mocap.stats().rate_hz == 0.0
    sim.step_to(0.5)
    assert mocap.stats().rate_hz == pytest.approx(100.0, rel=0.03)
    sim.step_to(3.0)
    stats = mocap.stats()
    assert isinstance(stats, MocapStats)
    assert stats.rate_hz == pytest.approx(100.0, abs=1.5)
    assert stats.dropouts == 0


def test_rate_meter_falls_to_zero_when_frames_stop():
    meter = RateMeter(window=1.0)
    for k in range(300):
        meter.add(k * 0.01)
    assert meter.rate(2.99) == pytest.approx(100.0, abs=1.5)
    assert meter.rate(3.5) == pytest.approx(49.0, abs=1.5)
    assert meter.rate(5.0) == 0.0


def test_same_seed_same_frames_other_seed_differs():
    def run(seed: int) -> np.ndarray:
        sim = FakeSim()
        mocap = make(sim, position_noise=0.001, attitude_noise=0.01, dropout_prob=0.2, latency=0.003, seed=seed)
        out = []
        for k in range(1, 401):
            sim.step_to(k * 0.0025)
            pose = mocap.latest(sim.t)
            if pose is not None:
                out.append(np.concatenate([[pose.t], pose.position, pose.quaternion]))
        return np.array(out)

    a, b, c = run(11), run(11), run(12)
    np.testing.assert_array_equal(a, b)
    assert a.shape != c.shape or not np.array_equal(a, c)


def test_pose_is_immutable_float64():
    pose = Pose(t=1, position=np.array([1, 2, 3], dtype=np.float32), quaternion=[1, 0, 0, 0])
    assert pose.position.dtype == np.float64 and isinstance(pose.t, float)
    with pytest.raises(ValueError):
        pose.position[0] = 5.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        pose.t = 2.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        Pose(t=0.0, position=np.zeros(2), quaternion=np.array([1.0, 0, 0, 0]))


def test_from_config_and_close():
    cfg = load_config(overrides={"sim.mocap_rate_hz": 50.0})
    sim = FakeSim()
    mocap = from_config(sim, cfg.sim)
    assert isinstance(mocap, SimulatedMocap)
    sim.step_to(0.1)
    # 50 Hz frames with the configured 4 ms latency: the 0.1 s frame is not visible yet.
    assert mocap.latest(0.1).t == pytest.approx(0.08)
    assert mocap.latest(0.1 + cfg.sim.mocap_latency).t == pytest.approx(0.1)
    assert mocap.stats().frames == 5
    mocap.close()
    sim.step_to(0.5)
    assert mocap.stats().frames == 5
