"""Online learning, flight side without a flight: window recorder, numpy one-step prediction, validation gate."""

from __future__ import annotations

import math
import subprocess
import sys

from dataclasses import replace

import numpy as np
import pytest

from cfknode.flight.adaptation import AdaptationEstimate
from cfknode.flight.learning.gate import (GateLimits, gate_pairs, one_step_rmse, operating_envelope, rollout_rmse,
                                         run_gate)
from cfknode.flight.learning.windows import WindowRecorder
from cfknode.models.modelfile import ModelFile, NetworkWeights, Normalisation
from cfknode.models.residual_np import ResidualQueue
from fakes import Est, Tick

RATE = 400.0
G = 9.81


def tick(t: float, z: float = 1.0, version: int = 0, source: str = "mpc") -> Tick:
    return Tick(t, Est(np.array([0.0, 0.0, z]), np.array([0.1, 0.0, 0.0])), np.zeros(3), source, version)


def constant_residual_model(r: np.ndarray, hidden: int = 4) -> ModelFile:
    """A one-network queue whose residual is the constant ``r`` (zero hidden weights, output bias only)."""
    w0, b0 = np.zeros((hidden, 6)), np.zeros(hidden)
    w1, b1 = np.zeros((3, hidden)), np.asarray(r, dtype=float)
    return ModelFile((hidden,), "tanh", 3, (NetworkWeights(((w0, b0), (w1, b1)), Normalisation.identity()),))


def linear_residual_model(gain_v: np.ndarray, gain_u: np.ndarray, eps: float = 1e-3) -> ModelFile:
    """r ~= gain_v @ v + gain_u @ u: tanh kept in its linear range by tiny input weights."""
    w0 = eps * np.eye(6)
    w1 = np.concatenate((gain_v, gain_u), axis=1) / eps
    return ModelFile((6,), "tanh", 3, (NetworkWeights(((w0, np.zeros(6)), (w1, np.zeros(3))), Normalisation.identity()),))


def limits(max_residual: float = 20.0) -> GateLimits:
    x, u = operating_envelope(1.3, np.array([-5.66, -5.66, -4.9]), np.array([5.66, 5.66, 3.83]))
    return GateLimits(max_residual, (0.25, 4.0), 1.0, x, u, max_cross_gain=0.2)


def flown_data(residual: np.ndarray, n: int = 240, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 400 Hz record of v' = u + residual with a wandering command and mocap-like velocity noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / RATE
    u = np.stack([0.5 * np.sin(3 * t), 0.3 * np.cos(2 * t), 0.2 * np.sin(5 * t)], axis=1)
    v = np.zeros((n, 3))
    for i in range(n - 1):
        v[i + 1] = v[i] + (u[i] + residual) / RATE
    p = np.cumsum(v, axis=0) / RATE
    x = np.concatenate((p, v + rng.normal(scale=2e-4, size=v.shape)), axis=1)
    return t, x, u


# --- recorder ----------------------------------------------------------------------------------


def test_recorder_cuts_windows_of_t_col() -> None:
    rec = WindowRecorder(t_col=0.5, rate_hz=RATE, ground_z=0.0)
    windows = [w for k in range(800) if (w := rec.add(tick(k / RATE))) is not None]
    assert len(windows) == 3  # 800 ticks = 2 s; each window takes 201 ticks (t_col spanned exactly)
    for w in windows:
        assert w.t1 - w.t0 == pytest.approx(0.5)
        assert w.x.shape == (201, 6) and w.u.shape == (201, 3)
    assert windows[1].t0 > windows[0].t1  # consecutive, no overlap
    assert [w.index for w in windows] == [1, 2, 3]


def test_recorder_skips_ground_and_non_mpc_ticks_and_breaks_the_run() -> None:
    rec = WindowRecorder(t_col=0.25, rate_hz=RATE, ground_z=0.0)
    assert rec.add(tick(0.0025, z=0.05)) is None  # below MIN_HEIGHT above the ground
    out = [rec.add(tick(0.01 + k / RATE)) for k in range(60)]
    assert not any(w is not None for w in out)  # 60 ticks < one 0.25 s window
    rec.add(tick(0.2, source="fallback"))  # a fallback tick ends the run: the partial window goes
    assert rec.discarded == 1
    windows = [w for k in range(120) if (w := rec.add(tick(0.3 + k / RATE))) is not None]
    assert len(windows) == 1 and windows[0].t0 == pytest.approx(0.3)


def test_a_lowered_floor_learns_a_surface_transit_the_default_skips() -> None:
    # 6 cm over the floor: ground effect, which a flight meant to learn it records (online.min_height).
    default = WindowRecorder(t_col=0.25, rate_hz=RATE, ground_z=0.0)
    lowered = WindowRecorder(t_col=0.25, rate_hz=RATE, ground_z=0.0, min_height=0.02)
    ticks = [tick(k / RATE, z=0.06) for k in range(120)]
    assert [w for k in ticks if (w := default.add(k)) is not None] == []
    assert len([w for k in ticks if (w := lowered.add(k)) is not None]) == 1
    assert lowered.add(tick(0.5, z=0.015)) is None  # under the lowered floor: still not learned from


def test_a_window_never_spans_a_model_change() -> None:
    rec = WindowRecorder(t_col=0.25, rate_hz=RATE, ground_z=0.0)
    windows = []
    for k in range(400):
        version = 0 if k < 150 else 1  # someone swapped the model between tick 149 and 150
        if k == 150:
            rec.reset()  # what the learner does on its own swaps
        w = rec.add(tick(k / RATE, version=version))
        if w is not None:
            windows.append(w)
    assert len(windows) == 3 and rec.discarded == 1  # 1 before the change, 2 after; the partial one dropped
    for w in windows:
        assert w.t1 < 150 / RATE or w.t0 >= 150 / RATE
        assert w.version == (0 if w.t1 < 150 / RATE else 1)
    # Even without the reset, a version change seen in the ticks ends the run.
    rec2 = WindowRecorder(t_col=0.25, rate_hz=RATE, ground_z=0.0)
    spans = [w for k in range(400) if (w := rec2.add(tick(k / RATE, version=int(k >= 150)))) is not None]
    assert len(spans) == 3 and all(w.t1 < 150 / RATE or w.t0 >= 150 / RATE for w in spans)


def test_recorder_starts_in_the_air_and_breaks_on_gaps() -> None:
    rec = WindowRecorder(t_col=0.25, rate_hz=RATE)  # no floor: a flight that starts in the air records at once
    windows = [w for k in range(101) if (w := rec.add(tick(k / RATE, z=1.0))) is not None]
    assert len(windows) == 1 and windows[0].t0 == pytest.approx(0.0)
    for k in range(50):
        rec.add(tick(0.3 + k / RATE, z=1.0))
    rec.add(tick(0.3 + 60 / RATE, z=1.0))  # ten ticks missing (flown blind, or by someone else)
    assert rec.discarded == 1


def layer(scale: float = 1.0, offset: tuple[float, float, float] = (0.0, 0.0, 0.0), stepping: bool = False) -> AdaptationEstimate:
    return AdaptationEstimate(np.asarray(offset, dtype=float), scale, np.ones(3), stepping=stepping)


def test_recorder_does_not_train_on_the_fast_layer_s_transient() -> None:
    rec = WindowRecorder(t_col=0.25, rate_hz=RATE, ground_z=0.0)
    # The layer still learning the mass (1.00 -> 1.05 over the window): not sent, counted.
    moving = [rec.add(replace(tick(k / RATE), layer=layer(scale=1.0 + 0.05 * k / 100))) for k in range(101)]
    assert all(w is None for w in moving) and rec.unsettled == 1 and rec.windows == 0
    # Settled (a 0.5 % wander): the next window is trained on.
    settled = [rec.add(replace(tick((101 + k) / RATE), layer=layer(scale=1.05 + 0.005 * (k % 2)))) for k in range(101)]
    assert settled[-1] is not None and rec.windows == 1
    # A tick while the layer tracks a step ends the run, like a saturated one.
    rec.add(replace(tick(202 / RATE), layer=layer(scale=1.05)))
    rec.add(replace(tick(203 / RATE), layer=layer(scale=1.05, stepping=True)))
    assert rec.discarded == 1


def test_recorder_fresh_data_and_long_runs() -> None:
    rec = WindowRecorder(t_col=0.25, rate_hz=RATE, ground_z=0.0)
    for k in range(8000):  # 20 s: the buffer (windows.KEEP_S) compacts several times
        rec.add(tick(k / RATE))
    t, x, u = rec.fresh(19.9)
    assert t[0] > 19.9 and t[-1] == pytest.approx(7999 / RATE)
    assert x.shape == (t.size, 6) and np.all(np.diff(t) > 0)
    assert rec.windows == 8000 // 101  # 101 ticks per 0.25 s window


# --- one-step prediction and gate ---------------------------------------------------------------


def test_gate_accepts_a_better_candidate_and_rejects_a_worse_one() -> None:
    r = np.array([0.0, 0.0, 3.0])
    t, x, u = flown_data(r)
    fresh = gate_pairs(t, x, u, filter_hz=8.0)
    good_file, bad_file = constant_residual_model(r), constant_residual_model(-r)
    good, bad = ResidualQueue.from_model_file(good_file), ResidualQueue.from_model_file(bad_file)

    better = run_gate(good_file, good, None, fresh, x, u, limits())
    assert better.accepted and better.reason == ""
    assert better.rmse_candidate < 0.2 * better.rmse_current
    assert better.rmse_nominal == better.rmse_current  # nominal is flying

    worse = run_gate(bad_file, bad, good, fresh, x, u, limits())
    assert not worse.accepted and "not better on held-out data" in worse.reason
    assert worse.rmse_candidate > worse.rmse_current

    same = run_gate(good_file, good, good, fresh, x, u, limits())
    assert not same.accepted  # "better than the model now flying", not as good


def test_beside_the_fast_layer_the_gate_judges_only_what_varies_and_asks_for_a_margin() -> None:
    # v' = u + (0.3 - 0.8 v_x) in x: a constant the layer holds anyway, and a drag-like term it cannot.
    rng = np.random.default_rng(1)
    n = 628  # one period of the x command: the velocity swings about 0
    t = np.arange(n) / RATE
    u = np.stack([0.8 * np.cos(4 * t) - 0.3, 0.3 * np.cos(2 * t), 0.2 * np.sin(5 * t)], axis=1)
    v = np.zeros((n, 3))
    drag = np.diag([-0.8, 0.0, 0.0])
    for i in range(n - 1):
        v[i + 1] = v[i] + (u[i] + [0.3, 0.0, 0.0] + drag @ v[i]) / RATE
    x = np.concatenate((np.cumsum(v, axis=0) / RATE, v + rng.normal(scale=2e-5, size=v.shape)), axis=1)
    fresh = gate_pairs(t, x, u, filter_hz=0.0)
    beside = replace(limits(), constant_free=True, min_improvement=0.05)
    const_file = constant_residual_model([0.3, 0.0, 0.0])
    const = ResidualQueue.from_model_file(const_file)
    # Alone, learning the constant is a better model; beside the layer, it adds nothing.
    assert run_gate(const_file, const, None, fresh, x, u, limits()).accepted
    verdict = run_gate(const_file, const, None, fresh, x, u, beside)
    assert not verdict.accepted and "data by 5%" in verdict.reason and "without constants" in verdict.reason
    assert verdict.rmse_candidate == pytest.approx(verdict.rmse_current, rel=1e-6)
    # The drag is what it keeps.
    drag_file = linear_residual_model(drag, np.zeros((3, 3)))
    kept = run_gate(drag_file, ResidualQueue.from_model_file(drag_file), None, fresh, x, u, beside)
    assert kept.accepted and kept.rmse_candidate < 0.5 * kept.rmse_current


def test_prediction_is_exact_for_the_true_constant_residual_and_accumulates_over_linked_pairs() -> None:
    r = np.array([0.0, 0.0, 2.0])
    t, x, u = flown_data(r)
    x[:, 3:6] = np.cumsum(np.vstack([np.zeros(3), (u[:-1] + r) / RATE]), axis=0)  # noise-free
    pairs = gate_pairs(t, x, u, filter_hz=0.0)
    true_model = ResidualQueue.from_model_file(constant_residual_model(r))
    assert one_step_rmse(true_model, pairs) < 1e-12
    assert one_step_rmse(None, pairs) == pytest.approx(2.0 / RATE / math.sqrt(3), rel=1e-9)
    assert rollout_rmse(None, pairs, 1) == one_step_rmse(None, pairs)
    assert rollout_rmse(true_model, pairs, 5) < 1e-12
    # The missing 2 m/s^2 adds up over five 2.5 ms steps; a constant is all of it, so without constants 0.
    assert rollout_rmse(None, pairs, 5) == pytest.approx(5 * 2.0 / RATE / math.sqrt(3), rel=1e-9)
    assert rollout_rmse(None, pairs, 5, constant_free=True) < 1e-12
    # 4 samples flown, 4 lost, and again: runs of 3 linked pairs, none of 5.
    keep = np.arange(t.size) % 8 < 4
    gappy = gate_pairs(t[keep], x[keep], u[keep], filter_hz=0.0)
    assert math.isnan(rollout_rmse(None, gappy, 5))
    assert rollout_rmse(None, gappy, 2) == pytest.approx(2 * 2.0 / RATE / math.sqrt(3), rel=1e-9)


def test_over_several_steps_a_state_dependent_gain_stands_clear_of_velocity_noise() -> None:
    # v' = u - 0.8 v_x with mocap-like velocity noise: over one 2.5 ms step the drag's share of the error
    # is about the noise's; over five it adds up while the noise at the two ends does not.
    rng = np.random.default_rng(3)
    n = 628
    t = np.arange(n) / RATE
    u = np.stack([0.8 * np.cos(4 * t), 0.3 * np.cos(2 * t), 0.2 * np.sin(5 * t)], axis=1)
    v = np.zeros((n, 3))
    drag = np.diag([-0.8, 0.0, 0.0])
    for i in range(n - 1):
        v[i + 1] = v[i] + (u[i] + drag @ v[i]) / RATE
    x = np.concatenate((np.cumsum(v, axis=0) / RATE, v + rng.normal(scale=2e-4, size=v.shape)), axis=1)
    fresh = gate_pairs(t, x, u, filter_hz=0.0)
    drag_q = ResidualQueue.from_model_file(linear_residual_model(drag, np.zeros((3, 3))))
    one = rollout_rmse(drag_q, fresh, 1, True) / rollout_rmse(None, fresh, 1, True)
    five = rollout_rmse(drag_q, fresh, 5, True) / rollout_rmse(None, fresh, 5, True)
    assert five < 0.8 * one
    beside = replace(limits(), constant_free=True, min_improvement=0.02, steps=5)
    drag_file = linear_residual_model(drag, np.zeros((3, 3)))
    assert run_gate(drag_file, drag_q, None, fresh, x, u, beside).accepted
    const_file = constant_residual_model([0.3, 0.0, 0.0])
    verdict = run_gate(const_file, ResidualQueue.from_model_file(const_file), None, fresh, x, u, beside)
    assert not verdict.accepted and "without constants, over 5 steps" in verdict.reason


def test_beside_the_fast_layer_a_gain_of_a_few_mm_per_s2_is_noise() -> None:
    """A drag of 0.8/s at these speeds removes ~0.1 m/s^2; the same network at 1/40 of it removes ~3 mm/s^2,
    what networks fitted to 0.1 s of noise scored in flight: the floor keeps the first and turns the second away."""
    rng = np.random.default_rng(3)
    n = 628
    t = np.arange(n) / RATE
    u = np.stack([0.8 * np.cos(4 * t), 0.3 * np.cos(2 * t), 0.2 * np.sin(5 * t)], axis=1)
    beside = replace(limits(), constant_free=True, min_improvement=0.02, steps=5, min_gain=0.01)
    for k, accepted in ((0.8, True), (0.02, False)):
        drag = np.diag([-k, 0.0, 0.0])
        v = np.zeros((n, 3))
        for i in range(n - 1):
            v[i + 1] = v[i] + (u[i] + drag @ v[i]) / RATE
        x = np.concatenate((np.cumsum(v, axis=0) / RATE, v + rng.normal(scale=1e-6, size=v.shape)), axis=1)
        fresh = gate_pairs(t, x, u, filter_hz=0.0)
        model = linear_residual_model(drag, np.zeros((3, 3)))
        verdict = run_gate(model, ResidualQueue.from_model_file(model), None, fresh, x, u, beside)
        assert verdict.rmse_candidate < 0.5 * verdict.rmse_current  # better by far more than the 2 % margin
        assert verdict.accepted == accepted, verdict.reason
        if not accepted:
            assert "m/s^2" in verdict.reason and "noise" in verdict.reason
    assert limits().min_gain == 0.0  # without a layer, the paper's gate: no floor


def test_gate_rejects_non_finite_and_unbounded_models() -> None:
    t, x, u = flown_data(np.zeros(3))
    fresh = gate_pairs(t, x, u, filter_hz=8.0)
    nan_file = constant_residual_model([0.0, 0.0, math.nan])
    verdict = run_gate(nan_file, ResidualQueue.from_model_file(nan_file), None, fresh, x, u, limits())
    assert not verdict.accepted and verdict.reason == "non-finite weights"

    big_file = constant_residual_model([0.0, 0.0, 25.0])
    verdict = run_gate(big_file, ResidualQueue.from_model_file(big_file), None, fresh, x, u, limits())
    assert not verdict.accepted and "exceeds knode.max_residual" in verdict.reason
    assert verdict.max_residual == pytest.approx(25.0)


def test_gate_rejects_implausible_dynamics_anywhere_in_the_envelope() -> None:
    t, x, u = flown_data(np.zeros(3))
    fresh = gate_pairs(t, x, u, filter_hz=8.0)
    # Half the control effectiveness is a 2x mass: plausible. A tenth is not: the MPC would saturate.
    for gain, ok in ((-0.5, True), (-0.9, False), (1.0, True), (3.5, False)):
        mf = linear_residual_model(np.zeros((3, 3)), gain * np.eye(3))
        verdict = run_gate(mf, ResidualQueue.from_model_file(mf), None, fresh, x, u, limits(max_residual=1e3))
        assert verdict.control_gain[0] == pytest.approx(1.0 + gain, abs=1e-3)
        assert ("control effectiveness" in verdict.reason) == (not ok), (gain, verdict.reason)
    # A residual growing with velocity is a phantom instability; drag (negative) is physics.
    for gain, ok in ((-0.5, True), (2.0, False)):
        mf = linear_residual_model(gain * np.eye(3), np.zeros((3, 3)))
        verdict = run_gate(mf, ResidualQueue.from_model_file(mf), None, fresh, x, u, limits(max_residual=1e3))
        assert verdict.velocity_gain == pytest.approx(gain, abs=1e-3)
        assert ("phantom instability" in verdict.reason) == (not ok), (gain, verdict.reason)
    # Thrust pointed where the MPC asks scales each axis alike: a climb bought by tilting (dr_z/du_x) is
    # spurious and the MPC would exploit it; a small rotation (yaw misalignment) is allowed.
    for coupling, ok in ((0.1, True), (0.3, False)):
        gain_u = np.zeros((3, 3))
        gain_u[2, 0] = coupling
        mf = linear_residual_model(np.zeros((3, 3)), gain_u)
        verdict = run_gate(mf, ResidualQueue.from_model_file(mf), None, fresh, x, u, limits(max_residual=1e3))
        assert verdict.cross_gain == pytest.approx(coupling, abs=1e-3)
        assert ("cross-coupling" in verdict.reason) == (not ok), (coupling, verdict.reason)
    # Bounded on the recent data but not at the corners of the input box, where the MPC saturates.
    mf = linear_residual_model(np.zeros((3, 3)), 0.6 * np.eye(3))
    verdict = run_gate(mf, ResidualQueue.from_model_file(mf), None, fresh, x, u, limits(max_residual=3.0))
    assert np.abs(ResidualQueue.from_model_file(mf).evaluate(x, u)).max() < 3.0
    assert not verdict.accepted and "exceeds knode.max_residual" in verdict.reason


def test_beside_the_layer_a_vertical_force_from_horizontal_speed_is_refused_and_the_climb_rate_term_is_not() -> None:
    """A take-off network's r_z fell 0.15-0.38 m/s^2 per m/s of horizontal speed; on the slow circle it doubled the
    vertical error. The thrust lost with climb rate (dr_z/dv_z) and drag along the velocity are on the diagonal."""
    t, x, u = flown_data(np.zeros(3))
    fresh = gate_pairs(t, x, u, filter_hz=8.0)
    bounded = replace(limits(max_residual=1e3), max_velocity_coupling=0.1)
    inflow_and_drag = np.diag([-0.25, -0.25, -0.4])
    spurious = inflow_and_drag.copy()
    spurious[2, 0] = -0.3
    for gain_v, ok in ((inflow_and_drag, True), (spurious, False)):
        mf = linear_residual_model(gain_v, np.zeros((3, 3)))
        model = ResidualQueue.from_model_file(mf)
        verdict = run_gate(mf, model, None, fresh, x, u, bounded)
        assert verdict.velocity_coupling == pytest.approx(abs(gain_v[2, 0]), abs=1e-3)
        assert ("velocity coupling" in verdict.reason) == (not ok), verdict.reason
        # Without the bound (the defaults) the coupling is reported and not judged.
        assert "velocity coupling" not in run_gate(mf, model, None, fresh, x, u, limits(max_residual=1e3)).reason


def test_beside_the_layer_a_vertical_force_growing_with_climb_rate_is_refused_and_the_inflow_is_not() -> None:
    """The motors' lag left in the targets reads as +tau w^2 v_z on an oscillation: a network fitted under a 150 ms
    lag learned dr_z/dv_z = +0.24. The air's inflow is negative, and a horizontal slope (the attitude loop's lag,
    learned at a line's turn-arounds) is not this bound's."""
    t, x, u = flown_data(np.zeros(3))
    fresh = gate_pairs(t, x, u, filter_hz=8.0)
    bounded = replace(limits(max_residual=1e3), max_climb_feedback=0.1)
    for diagonal, ok in (((-0.25, -0.25, -0.4), True), ((0.3, 0.0, -0.4), True), ((0.0, 0.0, 0.24), False)):
        mf = linear_residual_model(np.diag(diagonal), np.zeros((3, 3)))
        model = ResidualQueue.from_model_file(mf)
        verdict = run_gate(mf, model, None, fresh, x, u, bounded)
        assert verdict.climb_feedback == pytest.approx(diagonal[2], abs=1e-3)
        assert ("growing with climb rate" in verdict.reason) == (not ok), verdict.reason
        # Without the bound (the defaults) the slope is reported and not judged.
        assert "climb rate" not in run_gate(mf, model, None, fresh, x, u, limits(max_residual=1e3)).reason


def test_the_velocity_bounds_act_beside_the_layer_only() -> None:
    from cfknode.app.config import load_config
    from cfknode.app.learning import gate_limits

    cfg = load_config()
    assert gate_limits(cfg).max_velocity_coupling == 0.1 and gate_limits(cfg).max_climb_feedback == 0.1
    alone = load_config(overrides={"controller.adaptation": "none"})
    assert gate_limits(alone).max_velocity_coupling == math.inf and gate_limits(alone).max_climb_feedback == math.inf
    off = {"online.gate_layer_velocity_coupling": None, "online.gate_layer_climb_feedback": None}
    limits_off = gate_limits(load_config(overrides=off))  # null: any
    assert limits_off.max_velocity_coupling == math.inf and limits_off.max_climb_feedback == math.inf


def test_beside_the_layer_a_horizontal_effectiveness_far_from_one_is_refused_and_a_thrust_slope_is_not() -> None:
    import dataclasses

    t, x, u = flown_data(np.zeros(3))
    fresh = gate_pairs(t, x, u, filter_hz=8.0)
    beside = dataclasses.replace(limits(max_residual=1e3), horizontal_gain=(0.8, 1.25))
    # The attitude loop's lag behind a ramp, fitted as a static gain: the MPC would command 3x the tilt.
    for gain_u, ok in ((np.diag([-0.64, 0.0, 0.0]), False), (np.diag([-0.1, -0.1, 0.0]), True),
                       (np.diag([0.0, 0.0, -0.5]), True)):  # a thrust slope is the layer's thrust scale's
        mf = linear_residual_model(np.zeros((3, 3)), gain_u)
        verdict = run_gate(mf, ResidualQueue.from_model_file(mf), None, fresh, x, u, beside)
        assert ("horizontal control effectiveness" in verdict.reason) == (not ok), (gain_u, verdict.reason)
        without = run_gate(mf, ResidualQueue.from_model_file(mf), None, fresh, x, u, limits(max_residual=1e3))
        assert "horizontal" not in without.reason  # without a layer the broad bound alone
    # The bound is the default beside a layer: a candidate at 0.75 there flew a 1 m/s loop 2x worse.
    from cfknode.app.config import load_config
    from cfknode.app.learning import gate_limits

    assert gate_limits(load_config()).horizontal_gain == (0.8, 1.25)
    assert gate_limits(load_config(overrides={"controller.adaptation": "none"})).horizontal_gain == (0.0, math.inf)


def test_gate_without_held_out_data_rejects() -> None:
    t, x, u = flown_data(np.zeros(3))
    empty = gate_pairs(t[:1], x[:1], u[:1], filter_hz=8.0)
    mf = constant_residual_model([0.0, 0.0, 0.1])
    verdict = run_gate(mf, ResidualQueue.from_model_file(mf), None, empty, x, u, limits())
    assert not verdict.accepted and verdict.reason == "no held-out data to judge it on"


def test_flight_side_imports_no_torch() -> None:
    code = (
        "import sys, cfknode.flight.learning.learner, cfknode.app.learning, cfknode.models.trainer_process;"
        "print('torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
