"""The gate rejects a model that gains climb from tilting either way at the thrust limit, over the whole input box:
a curvature that a bound on each Jacobian misses (dr_z/du_y about -0.04 below level and +0.04 above)."""

from __future__ import annotations

import numpy as np
import pytest

from cfknode.flight.learning.gate import GateLimits, gate_pairs, operating_envelope, run_gate, tilt_climb
from cfknode.models.modelfile import ModelFile, NetworkWeights, Normalisation
from cfknode.models.residual_np import ResidualQueue
from test_online_gate import flown_data, linear_residual_model

BOX_LO, BOX_HI = np.array([-5.66, -5.66, -7.85]), np.array([5.66, 5.66, 5.28])  # the default vehicle's input box
U_IN = 3  # index of u_x in the network input (v, u)


def even_tilt_model(axis: int, gain_pos: float, gain_neg: float, scale: float = 0.5, centre: float = 2.0) -> ModelFile:
    """r_z rising with |u_axis| on both sides of level (zero at level): two tanh units, one per side.

    ``gain_pos``/``gain_neg`` scale the climb for positive / negative tilts, so the two sides may differ."""
    w0 = np.zeros((2, 6))
    w0[0, U_IN + axis], w0[1, U_IN + axis] = scale, -scale
    b0 = np.full(2, -scale * centre)
    w1 = np.zeros((3, 2))
    w1[2] = (gain_pos, gain_neg)
    b1 = np.array([0.0, 0.0, (gain_pos + gain_neg) * np.tanh(scale * centre)])
    return ModelFile((2,), "tanh", 3, (NetworkWeights(((w0, b0), (w1, b1)), Normalisation.identity()),))


def limits(max_tilt_climb: float) -> GateLimits:
    x, u = operating_envelope(1.3, BOX_LO, BOX_HI)
    return GateLimits(20.0, (0.25, 4.0), 1.0, x, u, max_cross_gain=0.2, max_tilt_climb=max_tilt_climb)


def largest_cross_slope(model: ResidualQueue, lim: GateLimits) -> float:
    _, _, ju = model.linearise(lim.envelope_x, lim.envelope_u)
    return float(np.abs(ju[:, ~np.eye(3, dtype=bool)]).max())


def _gate(mf: ModelFile, lim: GateLimits) -> tuple[bool, str]:
    """The gate on data flown by a plant with the candidate's own residual (so it is better than nominal there)."""
    t, x, u = flown_data(np.zeros(3), n=360)
    queue = ResidualQueue.from_model_file(mf)
    v = x[:, 3:6].copy()
    for i in range(len(t) - 1):  # re-fly the record with the model's residual: the candidate explains it exactly
        v[i + 1] = v[i] + (u[i] + queue.evaluate(x[i : i + 1], u[i : i + 1])[0]) / 400.0
    x = np.concatenate((x[:, :3], v), axis=1)
    verdict = run_gate(mf, queue, None, gate_pairs(t[200:], x[200:], u[200:], 0.0), x[:200], u[:200], lim)
    return verdict.accepted, verdict.reason


@pytest.mark.parametrize("axis", [0, 1])
def test_climb_from_tilt_either_way_is_rejected_though_each_slope_is_small(axis: int) -> None:
    mf = even_tilt_model(axis, 0.087, 0.080)
    queue = ResidualQueue.from_model_file(mf)
    lim = limits(0.05)
    slopes = largest_cross_slope(queue, lim)
    assert 0.035 < slopes < 0.2  # the linear cross-coupling check (0.2) lets it through
    # dr_z/du at +-2 m/s^2 of tilt: positive on one side, negative on the other (climb both ways).
    _, _, ju = queue.linearise(np.zeros((2, 6)), np.array([[0, 0, 5.28], [0, 0, 5.28]]) + np.outer([2, -2], np.eye(3)[axis]))
    assert ju[0, 2, axis] > 0.03 and ju[1, 2, axis] < -0.03
    assert tilt_climb(queue, lim.envelope_x, lim.envelope_u) > 0.1
    accepted, reason = _gate(mf, lim)
    assert not accepted and "tilting either way" in reason
    # Without the check, the same candidate passed every other test of the gate.
    accepted, reason = _gate(mf, limits(np.inf))
    assert accepted, reason


def test_a_tilt_that_costs_climb_or_an_odd_cross_term_passes() -> None:
    lim = limits(0.05)
    # Losing climb when tilting either way is what the clamp really does.
    losing = ResidualQueue.from_model_file(even_tilt_model(1, -0.087, -0.080))
    assert tilt_climb(losing, lim.envelope_x, lim.envelope_u) <= 0.0  # (x: no effect; y: a loss)
    # A yaw misalignment: r_z odd in u_y (gains one way, loses the other) is the linear check's business.
    odd = np.zeros((3, 3))
    odd[2, 1] = 0.15
    skew = ResidualQueue.from_model_file(linear_residual_model(np.zeros((3, 3)), odd))
    assert tilt_climb(skew, lim.envelope_x, lim.envelope_u) == pytest.approx(-0.0, abs=0.02)
    accepted, reason = _gate(linear_residual_model(np.zeros((3, 3)), odd), lim)
    assert accepted, reason
