"""Trajectories: segment layout, shapes, speed, smoothness, exact derivatives, batching."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cfknode.app.config import TrajectoryConfig, load_config
from cfknode.flight.trajectory import make_trajectory
from cfknode.kernel.reference import RefSamples, sample_twice

START = np.array([0.1, -0.2, 0.0])


def tcfg(**kw) -> TrajectoryConfig:
    base = dict(
        kind="circle",
        radius=0.5,
        speed=0.4,
        center=(0.3, -0.1),
        height=1.0,
        duration=12.0,
        takeoff_duration=3.0,
        settle_duration=1.0,
        land_duration=3.0,
        ramp_duration=2.0,
    )
    base.update(kw)
    return dataclasses.replace(load_config().trajectory, **base)


KINDS = [
    tcfg(kind="circle"),
    tcfg(kind="figure8", radius=0.6, speed=0.5),
    tcfg(kind="hover"),
    tcfg(kind="circle", ramp_duration=0.0),
    tcfg(kind="figure8", duration=3.0, ramp_duration=2.0),  # ramps meet in the middle
]


def dense(traj, step: float = 1e-3) -> tuple[np.ndarray, RefSamples]:
    t = np.arange(-0.5, traj.duration + 0.5, step)
    return t, traj.sample(t)


def test_segments_and_windows():
    cfg = tcfg()
    traj = make_trajectory(cfg, START)
    names = list(traj.segments)
    assert names == ["takeoff", "settle_start", "pattern", "settle_end", "land"]
    bounds = list(traj.segments.values())
    assert bounds[0][0] == 0.0 and bounds[-1][1] == pytest.approx(traj.duration)
    for (_, a1), (b0, _) in zip(bounds, bounds[1:]):
        assert a1 == b0
    assert traj.pattern_window == traj.segments["pattern"] == (4.0, 16.0)
    assert traj.duration == pytest.approx(3 + 1 + 12 + 1 + 3)


@pytest.mark.parametrize("cfg", KINDS, ids=lambda c: f"{c.kind}-ramp{c.ramp_duration}-d{c.duration}")
def test_derivatives_are_exact(cfg):
    traj = make_trajectory(cfg, START)
    h = 1e-5
    t = np.linspace(-0.2, traj.duration + 0.2, 4001)
    s0, sp, sm = traj.sample(t), traj.sample(t + h), traj.sample(t - h)
    fd_v = (sp.p - sm.p) / (2 * h)
    fd_a = (sp.v - sm.v) / (2 * h)
    np.testing.assert_allclose(fd_v, s0.v, atol=1e-6)
    if cfg.ramp_duration == 0.0:
        # The phase rate steps at the pattern ends (ramp 0 asks for it): skip those instants.
        t0, t1 = traj.pattern_window
        ok = (np.abs(t - t0) > 2 * h) & (np.abs(t - t1) > 2 * h)
        np.testing.assert_allclose(fd_a[ok], s0.a[ok], atol=1e-5)
    else:
        np.testing.assert_allclose(fd_a, s0.a, atol=1e-5)
    assert s0.p.shape == s0.v.shape == s0.a.shape == (len(t), 3)
    np.testing.assert_array_equal(s0.yaw, 0.0)


@pytest.mark.parametrize("cfg", [c for c in KINDS if c.ramp_duration > 0], ids=lambda c: c.kind)
def test_position_velocity_acceleration_are_continuous(cfg):
    traj = make_trajectory(cfg, START)
    step = 1e-4
    _, s = dense(traj, step)
    # A jump would show as a step much larger than the largest slope allows.
    for arr, bound in ((s.p, 2.0), (s.v, 5.0), (s.a, 20.0)):
        assert np.abs(np.diff(arr, axis=0)).max() < bound * step


def test_takeoff_from_start_to_pattern_start_and_hold():
    cfg = tcfg(kind="circle")
    traj = make_trajectory(cfg, START)
    first = np.array([cfg.center[0] + cfg.radius, cfg.center[1], cfg.height])
    s = traj.sample(np.array([-1.0, 0.0, 1.5, 3.0, 3.5, 4.0]))
    np.testing.assert_allclose(s.p[0], START)
    np.testing.assert_allclose(s.p[1], START)
    np.testing.assert_allclose(s.p[2], 0.5 * (START + first))  # quintic is symmetric
    np.testing.assert_allclose(s.p[3:], np.tile(first, (3, 1)), atol=1e-12)
    np.testing.assert_allclose(s.v[[0, 1, 3, 4, 5]], 0.0, atol=1e-12)
    np.testing.assert_allclose(s.a[[0, 1, 3, 4, 5]], 0.0, atol=1e-12)


def test_circle_full_speed_is_ccw_at_radius_and_speed():
    cfg = tcfg(kind="circle")
    traj = make_trajectory(cfg, START)
    t0, t1 = traj.pattern_window
    t = np.linspace(t0 + cfg.ramp_duration, t1 - cfg.ramp_duration, 500)
    s = traj.sample(t)
    rel = s.p[:, :2] - np.array(cfg.center)
    np.testing.assert_allclose(np.linalg.norm(rel, axis=1), cfg.radius, rtol=1e-12)
    np.testing.assert_allclose(s.p[:, 2], cfg.height)
    np.testing.assert_allclose(np.linalg.norm(s.v, axis=1), cfg.speed, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(s.a, axis=1), cfg.speed**2 / cfg.radius, rtol=1e-10)
    cross_z = rel[:, 0] * s.v[:, 1] - rel[:, 1] * s.v[:, 0]
    assert np.all(cross_z > 0)  # counter-clockwise seen from above


def test_speed_ramps_in_and_out():
    cfg = tcfg(kind="circle")
    traj = make_trajectory(cfg, START)
    t0, t1 = traj.pattern_window
    r = cfg.ramp_duration
    speed = np.linalg.norm(traj.sample(np.array([t0, t0 + 0.5 * r, t0 + r, t1 - r, t1 - 0.5 * r, t1])).v, axis=1)
    np.testing.assert_allclose(speed, [0, 0.5 * cfg.speed, cfg.speed, cfg.speed, 0.5 * cfg.speed, 0], atol=1e-12)
    t = np.linspace(t0, t1, 2000)
    assert np.linalg.norm(traj.sample(t).v, axis=1).max() <= cfg.speed * (1 + 1e-12)


def test_figure8_shape_and_peak_speed():
    cfg = tcfg(kind="figure8", radius=0.6, speed=0.5, duration=20.0)
    traj = make_trajectory(cfg, START)
    t0, t1 = traj.pattern_window
    s = traj.sample(np.linspace(t0, t1, 20001))
    rel = s.p[:, :2] - np.array(cfg.center)
    np.testing.assert_allclose(s.p[0], [cfg.center[0], cfg.center[1], cfg.height])  # starts at the centre
    assert np.abs(rel[:, 0]).max() == pytest.approx(cfg.radius, rel=1e-6)  # half-width
    assert np.abs(rel[:, 1]).max() == pytest.approx(cfg.radius / 2, rel=1e-6)
    assert np.linalg.norm(s.v, axis=1).max() == pytest.approx(cfg.speed, rel=1e-3)
    crossings = np.sum(np.linalg.norm(rel, axis=1) < 5e-3)
    assert crossings > 2  # passes the centre again, not just at the start


def test_hover_pattern_holds_the_point():
    cfg = tcfg(kind="hover")
    traj = make_trajectory(cfg, START)
    t0, t1 = traj.pattern_window
    s = traj.sample(np.linspace(t0 - 1.0, t1 + 1.0, 300))
    np.testing.assert_allclose(s.p, np.tile([cfg.center[0], cfg.center[1], cfg.height], (300, 1)))
    np.testing.assert_allclose(s.v, 0.0)


@pytest.mark.parametrize("cfg", KINDS[:3], ids=lambda c: c.kind)
def test_lands_straight_down_to_ground_and_holds(cfg):
    traj = make_trajectory(cfg, START)
    l0, l1 = traj.segments["land"]
    s = traj.sample(np.linspace(l0, l1 + 2.0, 400))
    np.testing.assert_allclose(s.p[:, :2], np.tile(s.p[0, :2], (400, 1)), atol=1e-12)
    assert np.all(np.diff(s.p[:, 2]) <= 1e-15)
    assert s.p[-1, 2] == 0.0 and np.all(s.v[-50:] == 0.0) and np.all(s.a[-50:] == 0.0)
    np.testing.assert_allclose(traj.final_position, s.p[-1])


@pytest.mark.parametrize("cfg", KINDS, ids=lambda c: f"{c.kind}-ramp{c.ramp_duration}")
def test_horizon_batches_match_single_samples(cfg):
    # The tick asks for 21 times spanning 1 s; windows straddle every segment boundary.
    traj = make_trajectory(cfg, START)
    for start in np.arange(-0.7, traj.duration + 0.3, 0.37):
        t = start + 0.05 * np.arange(21)
        batch = traj.sample(t)
        for k in (0, 7, 20):
            one = traj.sample(np.array([t[k]]))
            np.testing.assert_allclose(batch.p[k], one.p[0], atol=1e-12)
            np.testing.assert_allclose(batch.v[k], one.v[0], atol=1e-12)
            np.testing.assert_allclose(batch.a[k], one.a[0], atol=1e-12)
    # Unsorted input is fine too.
    t = np.array([10.0, 2.0, 17.5, 5.1])
    s = traj.sample(t)
    for k in range(4):
        np.testing.assert_allclose(s.p[k], traj.sample(t[k : k + 1]).p[0], atol=1e-12)


@pytest.mark.parametrize("cfg", KINDS, ids=lambda c: f"{c.kind}-ramp{c.ramp_duration}")
def test_two_previews_in_one_sample_are_each_preview_s_own(cfg):
    # The tick's preview and the one a command delay later, sampled in one call and split, as sampled apart:
    # off the instants where a ramp-free pattern's speed jumps (there either side is right, and a batch that
    # ends on one takes the side before it).
    traj = make_trajectory(cfg, START)
    for start in np.arange(-0.7, traj.duration + 0.3, 0.37) + 0.0011:
        t, later = start + 0.05 * np.arange(21), start + 0.0677 + 0.05 * np.arange(21)
        now, ahead = sample_twice(traj, t, later)
        for got, want in ((now, traj.sample(t)), (ahead, traj.sample(later))):
            np.testing.assert_array_equal(got.t, want.t)
            for k in ("p", "v", "a", "yaw"):
                np.testing.assert_allclose(getattr(got, k), getattr(want, k), atol=1e-12)
    alone, none = sample_twice(traj, t, None)
    assert none is None and np.array_equal(alone.p, traj.sample(t).p)


def test_default_config_builds():
    cfg = load_config()
    traj = make_trajectory(cfg.trajectory, cfg.sim.initial_position)
    assert traj.duration > cfg.trajectory.duration
    s = traj.sample(np.array([traj.pattern_window[0] + 5.0]))
    assert np.linalg.norm(s.v) == pytest.approx(cfg.trajectory.speed)


@pytest.mark.parametrize("kind, axis", [("line", 0), ("vertical", 2)])
def test_line_and_vertical_oscillate_along_their_axis_at_the_set_peak_speed(kind, axis):
    cfg = tcfg(kind=kind, radius=0.4, speed=0.8, duration=12.0, ramp_duration=1.0)
    traj = make_trajectory(cfg, START)
    t0, t1 = traj.pattern_window
    t = np.arange(t0, t1, 1e-3)
    ref = traj.sample(t)
    first = np.array([cfg.center[0], cfg.center[1], cfg.height])
    others = [k for k in range(3) if k != axis]
    assert np.allclose(ref.p[:, others], first[others]) and np.allclose(ref.v[:, others], 0.0)
    assert np.max(np.abs(ref.p[:, axis] - first[axis])) == pytest.approx(0.4, abs=1e-4)
    assert np.max(np.abs(ref.v[:, axis])) == pytest.approx(0.8, rel=1e-3)
    # The analytic velocity and acceleration are the position's derivatives (ramps included).
    assert np.allclose(np.gradient(ref.p[:, axis], t), ref.v[:, axis], atol=2e-3)
    assert np.allclose(np.gradient(ref.v[:, axis], t), ref.a[:, axis], atol=2e-2)


def test_phase_times_are_a_line_s_centre_crossings():
    # Phase at the end: w (duration - ramp) = 10.5 pi, so 10 centre crossings.
    cfg = tcfg(kind="line", radius=0.5, speed=1.0, duration=1.0 + 10.5 * np.pi * 0.5, ramp_duration=1.0)
    traj = make_trajectory(cfg, START)
    passes = traj.phase_times(np.pi)
    assert len(passes) == 10
    ref = traj.sample(passes)
    assert np.allclose(ref.p[:, 0], cfg.center[0], atol=1e-6)  # on the centre
    assert np.all(np.abs(ref.v[:, 0]) > 0.9)  # at (nearly) full speed, alternating direction
    assert np.all(np.sign(ref.v[1:, 0]) == -np.sign(ref.v[:-1, 0]))
    assert make_trajectory(tcfg(kind="hover"), START).phase_times(np.pi).size == 0
