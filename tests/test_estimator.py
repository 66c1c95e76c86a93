"""Velocity estimator: initialisation, convergence, accuracy on accelerating motion,
the commanded-acceleration input, latency compensation, stale frames, long gaps."""

from __future__ import annotations

import numpy as np
import pytest

from cfknode.app.config import EstimatorConfig, load_config
from cfknode.flight.estimator import StateEstimate, VelocityEstimator
from cfknode.mocap.source import Pose
from cfknode.models.quadrotor import euler_zyx_to_quat

TICK = 1.0 / 400.0
FRAME = 0.01
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


def cfg(**kw) -> EstimatorConfig:
    """The default estimator, except that the input given is the acceleration flown (no attitude lag), unless
    the test sets ``attitude_lag``."""
    kw.setdefault("attitude_lag", 0.0)
    return load_config(overrides={f"estimator.{k}": v for k, v in kw.items()}).estimator


def circle(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """0.5 m circle at 0.4 Hz (3.2 m/s^2 centripetal) with a vertical oscillation."""
    w, r = 2 * np.pi * 0.4, 0.5
    p = np.array([r * np.cos(w * t), r * np.sin(w * t), 1.0 + 0.1 * np.sin(3 * t)])
    v = np.array([-r * w * np.sin(w * t), r * w * np.cos(w * t), 0.3 * np.cos(3 * t)])
    a = np.array([-r * w * w * np.cos(w * t), -r * w * w * np.sin(w * t), -0.9 * np.sin(3 * t)])
    return p, v, a


def fly(
    est: VelocityEstimator,
    motion,
    seconds: float,
    noise: float = 3e-4,
    latency: float = 0.004,
    stamp_offset: float = 0.0,
    use_acc: bool = False,
    drop_every: int = 0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Run the 400 Hz tick against 100 Hz frames visible ``latency`` after sampling.
    ``stamp_offset`` is added to the frame stamps (hardware stamps arrival times).
    Returns position and velocity errors at every tick after the first second."""
    rng = np.random.default_rng(seed)
    n_frames = int(seconds / FRAME) + 2
    frames = []
    for k in range(1, n_frames):
        if drop_every and k % drop_every == 0:
            continue
        ts = k * FRAME
        frames.append((ts + latency, Pose(t=ts + stamp_offset, position=motion(ts)[0] + noise * rng.standard_normal(3), quaternion=LEVEL)))
    i, latest = 0, None
    p_err, v_err = [], []
    for j in range(1, int(seconds / TICK)):
        now = j * TICK
        while i < len(frames) and frames[i][0] <= now + 1e-12:
            latest = frames[i][1]
            i += 1
        est.update(latest)
        acc = motion(now - TICK)[2] if use_acc else None
        s = est.predict(now, acc)
        if s is not None and now > 1.0:
            p, v, _ = motion(now)
            p_err.append(s.p - p)
            v_err.append(s.v - v)
    return np.array(p_err), np.array(v_err)


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


def test_none_until_first_pose_then_starts_at_it():
    est = VelocityEstimator(cfg())
    assert est.predict(0.0) is None
    est.update(None)
    assert est.predict(0.01) is None
    q = euler_zyx_to_quat(0.0, 0.0, 0.7)
    est.update(Pose(t=0.01, position=np.array([1.0, 2.0, 0.0]), quaternion=q))
    s = est.predict(0.01)
    assert isinstance(s, StateEstimate)
    np.testing.assert_allclose(s.p, [1.0, 2.0, 0.0])
    np.testing.assert_allclose(s.v, 0.0)
    np.testing.assert_allclose(s.q, q)
    assert s.yaw == pytest.approx(0.7)
    assert s.t == 0.01


def test_constant_velocity_converges_without_noise():
    est = VelocityEstimator(cfg())
    v_true = np.array([0.5, -0.3, 0.2])
    p_err, v_err = fly(est, lambda t: (v_true * t, v_true, np.zeros(3)), 2.0, noise=0.0, latency=0.0)
    assert np.abs(v_err[-100:]).max() < 1e-6
    assert np.abs(p_err[-100:]).max() < 1e-8


def test_commanded_acceleration_removes_lag():
    without_p, without_v = fly(VelocityEstimator(cfg()), circle, 4.0)
    with_p, with_v = fly(VelocityEstimator(cfg()), circle, 4.0, use_acc=True)
    # Measured here: 0.088 and 0.016 m/s rms; finite differences of the same frames: ~0.075.
    assert rms(with_v) < 0.025
    assert rms(without_v) < 0.12
    assert rms(with_v) < 0.3 * rms(without_v)
    assert rms(with_p) < 1e-3
    assert rms(without_p) < 2e-3


def test_attitude_lag_predicts_with_the_acceleration_flown() -> None:
    """A vehicle whose horizontal acceleration is its command through a 0.17 s first-order lag (the attitude
    loop): the filter told that lag tracks its velocity; fed the command as if it acted at once, it leads."""
    tau, cmd = 0.17, lambda t: np.array([2.0 * np.sin(3.0 * t), 1.5 * np.cos(2.0 * t), -0.9 * np.sin(3 * t)])
    dt = 1e-4
    ts = np.arange(0.0, 4.2, dt)
    a = np.zeros((ts.size, 3))
    for i in range(1, ts.size):  # the flown acceleration: x, y lagged, z at once
        a[i, :2] = a[i - 1, :2] + (1.0 - np.exp(-dt / tau)) * (cmd(ts[i - 1])[:2] - a[i - 1, :2])
        a[i, 2] = cmd(ts[i])[2]
    v = np.cumsum(a, axis=0) * dt
    p = np.cumsum(v, axis=0) * dt

    def motion(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        i = min(int(round(t / dt)), ts.size - 1)
        return p[i], v[i], cmd(t)  # the "acceleration" the test feeds is the command

    # Without mocap noise, so what is left is the model's error alone.
    _, lagged = fly(VelocityEstimator(cfg(attitude_lag=tau)), motion, 4.0, noise=0.0, use_acc=True)
    _, at_once = fly(VelocityEstimator(cfg()), motion, 4.0, noise=0.0, use_acc=True)
    assert rms(lagged[:, :2]) < 0.2 * rms(at_once[:, :2])
    # z is not lagged (the motors are an order faster than the attitude loop): the same either way.
    np.testing.assert_allclose(lagged[:, 2], at_once[:, 2], atol=1e-12)


def test_attitude_lag_state_starts_again_at_reset() -> None:
    est = VelocityEstimator(cfg(attitude_lag=0.17))
    est.update(Pose(t=0.0, position=np.zeros(3), quaternion=LEVEL))
    for j in range(1, 41):
        s = est.predict(j * TICK, np.array([1.0, 0.0, 1.0]))
    # 0.1 s of a 1 m/s^2 command through the lag, held over each tick: the flown acceleration after tick j
    # is 1 - exp(-j TICK / tau), about 0.45 at 0.1 s; z at once.
    k = 1.0 - np.exp(-TICK / 0.17)
    flown = 1.0 - (1.0 - k) ** np.arange(1, 41)
    assert s.v[0] == pytest.approx(TICK * flown.sum(), rel=1e-9)
    assert s.v[2] == pytest.approx(0.1, rel=1e-9)
    est.reset()
    est.update(Pose(t=1.0, position=np.zeros(3), quaternion=LEVEL))
    s = est.predict(1.0 + TICK, np.array([1.0, 0.0, 0.0]))
    assert s.v[0] == pytest.approx(TICK * k, rel=1e-9)  # from rest again, not from the 0.45 before the reset


def test_beats_finite_differences_with_known_input():
    rng = np.random.default_rng(3)
    ts = np.arange(1, 401) * FRAME
    pos = np.array([circle(t)[0] for t in ts]) + 3e-4 * rng.standard_normal((len(ts), 3))
    fd = np.diff(pos, axis=0) / FRAME  # no lag charged: compared at the interval midpoint
    truth = np.array([circle(t)[1] for t in 0.5 * (ts[1:] + ts[:-1])])
    _, v_err = fly(VelocityEstimator(cfg()), circle, 4.0, use_acc=True, seed=3)
    assert rms(v_err) < 0.5 * rms(fd - truth)


def test_repeated_and_older_poses_are_ignored():
    a, b = VelocityEstimator(cfg()), VelocityEstimator(cfg())
    poses = [Pose(t=0.01 * k, position=np.array([0.02 * k, 0.0, 1.0]), quaternion=LEVEL) for k in range(1, 6)]
    for k, pose in enumerate(poses):
        a.update(pose)
        b.update(pose)
        b.update(pose)  # same frame again (latest() returns it until a newer one)
        if k > 0:
            b.update(poses[k - 1])  # an older one
        sa, sb = a.predict(pose.t + 0.003), b.predict(pose.t + 0.003)
        np.testing.assert_array_equal(sa.p, sb.p)
        np.testing.assert_array_equal(sa.v, sb.v)


def test_latency_compensation_for_arrival_stamped_frames():
    # Hardware stamps frames on arrival: stamp = sample time + 20 ms.
    v_true = np.array([1.0, 0.0, 0.0])
    motion = lambda t: (v_true * t, v_true, np.zeros(3))  # noqa: E731
    lat = 0.02
    naive_p, _ = fly(VelocityEstimator(cfg(latency=0.0)), motion, 2.0, latency=lat, stamp_offset=lat)
    comp_p, comp_v = fly(VelocityEstimator(cfg(latency=lat)), motion, 2.0, latency=lat, stamp_offset=lat)
    assert np.abs(naive_p[-100:, 0]).mean() == pytest.approx(lat * 1.0, rel=0.1)  # 20 mm behind
    assert np.abs(comp_p[-100:]).max() < 2e-3
    assert np.abs(comp_v[-100:]).max() < 0.03


def test_dropped_frames_and_a_long_gap():
    est = VelocityEstimator(cfg())
    _, v_err = fly(est, circle, 3.0, use_acc=True, drop_every=3)
    assert rms(v_err) < 0.03
    # A 0.5 s gap (200 predictions, beyond the history kept) then frames again.
    est = VelocityEstimator(cfg())
    v_true = np.array([0.4, 0.1, 0.0])
    for k in range(1, 101):
        est.update(Pose(t=k * FRAME, position=v_true * k * FRAME, quaternion=LEVEL))
        for j in range(4):
            est.predict(k * FRAME + (j + 1) * TICK)
    now = 1.0
    for _ in range(200):
        now += TICK
        s = est.predict(now)
    np.testing.assert_allclose(s.p, v_true * now, atol=1e-6)  # dead-reckons at constant velocity
    for k in range(151, 201):
        est.update(Pose(t=k * FRAME, position=v_true * k * FRAME, quaternion=LEVEL))
        s = est.predict(k * FRAME + 0.001)
    assert np.all(np.isfinite(s.p)) and np.abs(s.v - v_true).max() < 1e-4


def test_estimates_are_not_aliased():
    est = VelocityEstimator(cfg())
    est.update(Pose(t=0.01, position=np.zeros(3), quaternion=LEVEL))
    s1 = est.predict(0.0125, np.array([1.0, 0.0, 0.0]))
    p1 = s1.p.copy()
    est.update(Pose(t=0.02, position=np.array([0.01, 0.0, 0.0]), quaternion=LEVEL))
    est.predict(0.0225, np.array([1.0, 0.0, 0.0]))
    np.testing.assert_array_equal(s1.p, p1)
