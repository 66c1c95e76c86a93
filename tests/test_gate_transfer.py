"""Beside the fast layer the gate judges a candidate by what transfers: on held-out data it must remove
part of what the layer leaves (the score `cfknode model check` reports), or it is never flown."""

from __future__ import annotations

import numpy as np
import pytest

from cfknode.flight.learning.gate import gate_pairs, layer_scores, run_gate
from cfknode.models.residual_np import ResidualQueue
from test_online_gate import RATE, limits, linear_residual_model

LAYER_HZ = ((0.5, 1.0), (0.5, 0.5))  # the default layer's observer and output cut-offs


def manoeuvre(slope: float, seed: int, n: int = 800) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """400 Hz of v' = u + slope * v_x e_x + a constant, with a command that swings v_x both ways."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / RATE
    w = rng.uniform(4.0, 7.0)
    u = np.stack([2.0 * np.sin(w * t), 0.4 * np.cos(2 * t), 0.2 * np.sin(5 * t)], axis=1)
    v = np.zeros((n, 3))
    for i in range(n - 1):
        v[i + 1] = v[i] + (u[i] + np.array([slope * v[i, 0], 0.0, 0.0]) + [0.05, -0.03, 0.1]) / RATE
    p = np.cumsum(v, axis=0) / RATE
    return t, np.concatenate((p, v + rng.normal(scale=2e-4, size=v.shape)), axis=1), u


def slope_model(slope: float) -> tuple[object, ResidualQueue]:
    mf = linear_residual_model(np.diag([slope, 0.0, 0.0]), np.zeros((3, 3)))
    return mf, ResidualQueue.from_model_file(mf)


def test_a_term_that_is_there_scores_and_one_that_is_not_does_not():
    t, x, u = manoeuvre(-0.6, seed=1)
    fresh = gate_pairs(t, x, u, 8.0)
    _, true_model = slope_model(-0.6)
    _, wrong_model = slope_model(+0.6)
    assert layer_scores(true_model, None, fresh, LAYER_HZ)[0][0] > 0.5  # the drag the layer is too slow for
    assert layer_scores(wrong_model, None, fresh, LAYER_HZ)[0][0] < 0.0
    # A plant without the slope: the slope a model learned elsewhere makes things worse, not better.
    t, x, u = manoeuvre(0.0, seed=2)
    assert layer_scores(true_model, None, gate_pairs(t, x, u, 8.0), LAYER_HZ)[0][0] < 0.0


def test_the_gate_rejects_a_slope_learned_on_another_manoeuvre_and_flies_one_that_transfers():
    lim = limits()
    import dataclasses

    beside = dataclasses.replace(lim, constant_free=True, steps=5, layer_hz=LAYER_HZ)
    mf, model = slope_model(-0.6)
    # Fresh data from a manoeuvre where the vehicle has no such drag: the model learned it elsewhere.
    t, x, u = manoeuvre(0.0, seed=3)
    verdict = run_gate(mf, model, None, gate_pairs(t[400:], x[400:], u[400:], 8.0), x[:400], u[:400], beside)
    assert not verdict.accepted
    # Fresh data that does have it: the same model passes every rule, the transfer score included.
    t, x, u = manoeuvre(-0.6, seed=4)
    verdict = run_gate(mf, model, None, gate_pairs(t[400:], x[400:], u[400:], 8.0), x[:400], u[:400], beside)
    assert verdict.accepted, verdict.reason


def test_the_transfer_rule_alone_rejects_what_explains_nothing_beyond_the_layer():
    import dataclasses

    # Every other comparison relaxed: only the score beyond the layer decides.
    lenient = dataclasses.replace(limits(), constant_free=True, min_improvement=-1000.0, min_gain=-np.inf,
                                  layer_hz=LAYER_HZ)
    mf, model = slope_model(-0.6)
    t, x, u = manoeuvre(0.0, seed=3)
    verdict = run_gate(mf, model, None, gate_pairs(t[400:], x[400:], u[400:], 8.0), x[:400], u[:400], lenient)
    assert not verdict.accepted and "explains nothing beyond the fast layer" in verdict.reason
    without = run_gate(mf, model, None, gate_pairs(t[400:], x[400:], u[400:], 8.0), x[:400], u[:400],
                       dataclasses.replace(lenient, layer_hz=None))
    assert without.accepted, without.reason  # the rule, not another, turned it away


def test_a_minimum_score_refuses_a_candidate_that_removes_too_little_of_what_the_layer_leaves():
    import dataclasses

    lenient = dataclasses.replace(limits(), constant_free=True, min_improvement=-1000.0, min_gain=-np.inf,
                                  layer_hz=LAYER_HZ)
    t, x, u = manoeuvre(-0.6, seed=4)
    fresh = gate_pairs(t[400:], x[400:], u[400:], 8.0)
    mf, small = slope_model(-0.06)  # a tenth of the drag that is there: a small positive score
    score = float(layer_scores(small, None, fresh, LAYER_HZ)[0][0])
    assert 0.0 < score < 0.3
    assert run_gate(mf, small, None, fresh, x[:400], u[:400], lenient).accepted
    strict = dataclasses.replace(lenient, min_score=0.3)
    verdict = run_gate(mf, small, None, fresh, x[:400], u[:400], strict)
    assert not verdict.accepted and "explains nothing beyond the fast layer" in verdict.reason
    mf, whole = slope_model(-0.6)
    assert run_gate(mf, whole, None, fresh, x[:400], u[:400], strict).accepted


def test_a_vertical_force_growing_with_climb_rate_does_not_fly_and_the_horizontal_term_beside_it_does():
    import dataclasses

    lenient = dataclasses.replace(limits(), constant_free=True, min_improvement=-1000.0, min_gain=-np.inf,
                                  layer_hz=LAYER_HZ, max_climb_feedback=0.1)
    t, x, u = manoeuvre(-0.6, seed=4)
    fresh = gate_pairs(t[400:], x[400:], u[400:], 8.0)
    # The drag that is there, and the motors' lag read as a vertical slope (+0.25 per m/s of climb).
    mf = linear_residual_model(np.diag([-0.6, 0.0, 0.25]), np.zeros((3, 3)))
    verdict = run_gate(mf, ResidualQueue.from_model_file(mf), None, fresh, x[:400], u[:400], lenient)
    assert verdict.accepted, verdict.reason
    assert verdict.climb_feedback == pytest.approx(0.25, abs=1e-3)
    assert verdict.score[0] > 0.5 and verdict.score[2] <= 0.0  # flown on x, not on z
    # Only the vertical slope: nothing left to fly, refused for the slope.
    mf = linear_residual_model(np.diag([0.0, 0.0, 0.25]), np.zeros((3, 3)))
    verdict = run_gate(mf, ResidualQueue.from_model_file(mf), None, fresh, x[:400], u[:400], lenient)
    assert not verdict.accepted and "growing with climb rate" in verdict.reason
