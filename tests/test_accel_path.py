"""The accelerometer's fast path (flight/adaptation/accel_path.py): the residual it measures (rotation, gravity),
its filters (the Butterworth, the complement of the frames observer), its freezing on stale or unusable samples,
and where the layer adds it. The closed-loop comparison on the realistic plant is the last test (slow)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cfknode.flight.adaptation.accel_path import (
    ACCEL_RANGE, AccelTuning, accel_part, accel_start, accel_step, biquad_rest, biquad_step, butterworth2,
    saturated, world_residual,
)
from cfknode.flight.adaptation.layer import FastAdaptation, LoopExtras
from cfknode.flight.adaptation.loop import body_z
from cfknode.flight.adaptation.settings import AdaptationSettings
from cfknode.sim_backend.accelerometer import specific_force

G = 9.81
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


def _quat(axis: tuple[float, float, float], angle: float) -> np.ndarray:
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    return np.concatenate(([math.cos(angle / 2)], math.sin(angle / 2) * a))


def _tuning(cutoff: float = 5.0, stale: float = 0.03) -> AccelTuning:
    two_pi = 2.0 * math.pi
    return AccelTuning(cutoff, two_pi * np.array([0.5, 0.5, 1.0]), two_pi * np.array([0.5, 0.5, 0.5]), 2.0, stale)


def test_hover_reads_gravity_and_leaves_no_residual() -> None:
    d = world_residual(LEVEL, np.array([0.0, 0.0, G]), G, np.zeros(3))
    assert np.allclose(d, 0.0, atol=1e-12)


@pytest.mark.parametrize("axis, angle", [((1, 0, 0), 0.5), ((0, 1, 0), -0.3), ((0.3, -0.2, 1.0), 1.1)])
def test_the_residual_is_the_world_acceleration_the_simulated_sensor_was_given(axis, angle) -> None:
    """The simulator rotates a world acceleration into the body (R^T (a + g e_z)); the fast path rotates back and
    removes gravity: what comes out is the acceleration less the model's, whatever the attitude."""
    q = _quat(axis, angle)
    a_world = np.array([0.7, -1.2, 0.4])
    state = [0.0] * 6 + q.tolist() + [0.0] * 7
    f_body = np.array(specific_force(state, a_world.tolist(), G))
    model = np.array([0.5, -1.0, 0.1])
    assert np.allclose(world_residual(q, f_body, G, model), a_world - model, atol=1e-12)


def test_a_tilted_thrust_that_the_model_predicts_leaves_no_residual() -> None:
    """Thrust k along the body z axis, as the model computes it with ``body_z``: only what is not thrust remains,
    so an error of the attitude only enters multiplied by the (small) residual."""
    q = _quat((1.0, 1.0, 0.0), 0.4)
    k = 11.0
    model = k * body_z(q) - np.array([0.0, 0.0, G])
    assert np.allclose(world_residual(q, np.array([0.0, 0.0, k]), G, model), 0.0, atol=1e-12)
    drag = world_residual(q, np.array([-0.3, 0.0, k]), G, model)  # body x force: along body x in the world
    assert np.allclose(drag, -0.3 * np.array([1 - 2 * q[2] ** 2, 2 * q[1] * q[2], -2 * q[0] * q[2]]), atol=1e-12)


def test_butterworth_has_unit_dc_gain_and_half_power_at_the_cutoff() -> None:
    dt = 0.01
    for cutoff in (1.0, 2.0, 5.0, 8.0):
        c = butterworth2(cutoff, dt)
        assert (c.b0 + c.b1 + c.b2) / (1.0 + c.a1 + c.a2) == pytest.approx(1.0, abs=1e-12)
        z = np.exp(-1j * 2.0 * math.pi * cutoff * dt)
        h = (c.b0 + c.b1 * z + c.b2 * z * z) / (1.0 + c.a1 * z + c.a2 * z * z)
        assert abs(h) == pytest.approx(1.0 / math.sqrt(2.0), rel=1e-9)


def test_the_filter_started_at_rest_stays_on_a_constant_input() -> None:
    c = butterworth2(5.0, 0.01)
    x = np.array([0.3, -0.2, 1.5])
    state = biquad_rest(c, x)
    for _ in range(50):
        y, state = biquad_step(c, state, x)
        assert np.allclose(y, x, atol=1e-12)


def _run(signal, tuning: AccelTuning, n: int, dt: float = 0.01) -> np.ndarray:
    state = accel_start(0.0, signal(0.0), tuning)
    parts = []
    for i in range(1, n):
        t = i * dt
        state = accel_step(state, t, signal(t), tuning)
        parts.append(state.part.copy())
    return np.array(parts)


def test_a_constant_offset_such_as_a_bias_is_left_to_the_frames_observer() -> None:
    """A bias (or a thrust map's error) appears at once: the fast path passes its transient, then gives it back
    to the slow observer, whose own poles it subtracts: after 10 s nothing of it is left."""
    bias = np.array([0.2, -0.2, 0.3])
    parts = _run(lambda t: bias if t > 0.0 else np.zeros(3), _tuning(), 1001)
    assert np.max(np.abs(parts[:50])) > 0.1  # the fast part carried it while the observer had not learned it
    assert np.allclose(parts[-1], 0.0, atol=0.01)


def test_a_fast_disturbance_passes_below_the_cutoff_and_is_cut_above() -> None:
    """A 3 Hz disturbance at an 8 Hz cutoff: the fast part carries nearly all of it (the observer's share is
    small there); at a 1 Hz cutoff most of it is cut."""
    wave = lambda t: np.array([1.0, 0.0, 0.0]) * math.sin(2.0 * math.pi * 3.0 * t)  # noqa: E731
    fast = _run(wave, _tuning(8.0), 1000)[-300:, 0]
    slow = _run(wave, _tuning(1.0), 1000)[-300:, 0]
    assert 0.8 < np.sqrt(2.0) * np.std(fast) < 1.1
    assert np.sqrt(2.0) * np.std(slow) < 0.2


def test_the_part_is_bounded() -> None:
    parts = _run(lambda t: np.array([50.0, -50.0, 0.0]) * (t > 0.0), _tuning(8.0), 30)
    assert np.max(np.abs(parts)) == pytest.approx(2.0)


def test_stale_samples_withdraw_the_part_and_a_gap_restarts_the_filters() -> None:
    tuning = _tuning(stale=0.03)
    state = accel_start(0.0, np.zeros(3), tuning)
    state = accel_step(state, 0.01, np.array([1.0, 0.0, 0.0]), tuning)
    part = state.part.copy()
    assert part[0] > 0.0
    assert np.array_equal(accel_part(state, 0.035, tuning), part)  # held between samples
    assert accel_part(state, 0.05, tuning) is None  # the newest sample is too old: withdrawn, not held
    after_gap = accel_step(state, 0.2, np.array([1.0, 0.0, 0.0]), tuning)
    assert np.array_equal(after_gap.part, np.zeros(3))  # restarted at rest: the gap is not read as news
    assert accel_part(None, 0.0, tuning) is None


def test_a_sample_that_is_not_a_number_freezes_the_filters() -> None:
    tuning = _tuning()
    state = accel_step(accel_start(0.0, np.zeros(3), tuning), 0.01, np.array([1.0, 0.0, 0.0]), tuning)
    assert accel_step(state, 0.02, np.array([math.nan, 0.0, 0.0]), tuning) is state


def test_a_sample_at_the_sensor_range_is_saturated() -> None:
    assert not saturated(np.array([0.0, 0.0, G]))
    assert saturated(np.array([0.0, ACCEL_RANGE, G]))
    assert saturated(np.array([0.0, 0.0, math.inf]))
    assert saturated(np.array([math.nan, 0.0, G]))


def _layer() -> FastAdaptation:
    s = AdaptationSettings(
        mode="dob", bandwidth_hz=1.0, bandwidth_xy_hz=0.5, predictor_gain=20.0, adaptation_gain=400.0,
        thrust_rate=0.0, axis_rate=0.0, max_offset=1.0, thrust_scale_bounds=(0.4, 2.5), axis_gain_bounds=(0.8, 1.25),
        stale_pose_s=0.05, rebase_window_s=0.25, thrust_lag_s=None, thrust_lag_candidates_s=(), step_threshold=0.0,
        step_bandwidth_hz=10.0, step_thrust_rate=0.0, step_hold_s=0.3, oracle_delay_s=0.0, output_bandwidth_hz=0.5,
        output_bandwidth_xy_hz=0.5, offset_deadband=0.0, engage_level=0.0, engage_slow_level=0.03,
        engage_slow_s=2.0, release_s=0.3, step_max_s=1.0, wake_radius=0.0, accel_cutoff_hz=5.0, accel_max_offset=2.0,
        accel_stale_s=0.03, model_coefficients=True, coefficient_bounds=(0.0, 1.5), coefficient_memory_s=4.0,
        coefficient_prior=0.05, model_mean_s=1.0, model_min_score=0.002)
    return FastAdaptation(s, 400.0, G)


def test_the_layer_adds_the_part_bounded_and_drops_it_when_frozen() -> None:
    layer = _layer()
    v, u = np.zeros(3), np.zeros(3)
    for i in range(4):
        layer.update(i / 400.0, v, None, u, u)
    base = layer.estimate.offset.copy()
    part = np.array([0.3, -0.2, 5.0])
    est = layer.update(4 / 400.0, v, None, u, u, extras=LoopExtras(accel_part=part))
    assert np.allclose(est.offset[:2], base[:2] + part[:2], atol=1e-3)
    assert est.offset[2] == pytest.approx(1.0)  # max_offset bounds the sum
    frozen = layer.update(0.5, v, None, u, u, pose_fresh=False, extras=LoopExtras(accel_part=part))
    assert frozen.frozen and np.max(np.abs(frozen.offset)) < 0.01  # the fast part is not held while blind



def test_through_the_cflib_log_path_the_fast_path_measures_the_plants_acceleration(tmp_path) -> None:
    """A short flight on the realistic plant with the fast path on (8 Hz): it lands, and each accelerometer sample
    the loop saw, rotated with the estimate's attitude less gravity, is the plant's true acceleration at the
    sample's stamp, up to the sensor's noise (0.3 m/s^2), with no bias from the rotation or the stamps.

    What the fast path does to the tracking is in docs/results.md: on this plant it does not beat the frames
    observer across seeds, so no test claims it does."""
    from cfknode.app.config import load_config
    from cfknode.app.logs.reader import read_columns
    from cfknode.app.mission import run_flight

    overrides = {"sim.aero": "realistic", "trajectory.duration": 4.0, "trajectory.takeoff_duration": 1.5,
                 "trajectory.settle_duration": 0.3, "trajectory.land_duration": 1.5, "trajectory.ramp_duration": 0.5,
                 "controller.adaptation_settings.accel_cutoff_hz": 8.0, "log.dir": str(tmp_path)}
    result = run_flight(load_config(overrides=overrides), name_hint="accel")
    s = result.summary
    assert result.outcome.message == "flight complete: landed"
    assert s.extra["fence_excursion_m"] == 0.0 and s.extra["fallback_ticks"] == 0
    log = read_columns(s.log_path, {"/state": ("p", "q", "v_true", "imu_t", "imu_f")})
    t = log.times("/state")
    q, v_true = log.array("/state", "q").astype(float), log.array("/state", "v_true").astype(float)
    imu_t, imu_f = log.array("/state", "imu_t").astype(float), log.array("/state", "imu_f").astype(float)
    airborne = log.array("/state", "p").astype(float)[:, 2] > 0.3
    a_true = np.gradient(v_true, t, axis=0)
    ticks = np.flatnonzero(airborne & np.isfinite(imu_t))
    ticks = ticks[np.unique(imu_t[ticks], return_index=True)[1]]  # one tick per sample
    assert len(ticks) > 300
    at_stamp = np.searchsorted(t, imu_t[ticks])  # the tick at the sample's stamp
    error = np.array([world_residual(q[i], imu_f[i], G, np.zeros(3)) for i in ticks]) - a_true[at_stamp]
    assert np.all(np.abs(error.mean(axis=0)) < 0.05), error.mean(axis=0)
    assert np.all((0.2 < error.std(axis=0)) & (error.std(axis=0) < 0.4)), error.std(axis=0)
