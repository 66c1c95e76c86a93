"""Below the fast layer's floor margin the layer measures nothing (it holds its estimate), so near the floor,
where a model may learn the ground effect, the vertical is the model's: the MPC flies its whole residual, and
the gate judges a candidate with its constants, as without a layer."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from cfknode.flight.adaptation.composite import CoefficientSettings, ModelCoefficients
from cfknode.flight.learning.gate import gate_pairs, run_gate
from cfknode.flight.learning.windows import WindowRecorder
from cfknode.flight.mpc_problem import ResidualLinearisation
from cfknode.models.residual_np import ResidualQueue
from test_gate_transfer import LAYER_HZ
from test_online_gate import RATE, flown_data, limits, linear_residual_model


def constant_model(c: tuple[float, float, float]) -> tuple[object, ResidualQueue]:
    """A model whose residual is the constant ``c`` (a bias on the output layer)."""
    mf = linear_residual_model(np.zeros((3, 3)), np.zeros((3, 3)))
    net = mf.networks[0]
    (w0, b0), (w1, _) = net.layers
    mf = dataclasses.replace(mf, networks=(dataclasses.replace(net, layers=((w0, b0), (w1, np.array(c)))),))
    return mf, ResidualQueue.from_model_file(mf)


def test_near_the_floor_the_vertical_is_the_models_whole_and_the_layers_held_offset_is_not_added() -> None:
    coeffs = ModelCoefficients(CoefficientSettings((0.0, 1.5), 4.0, 0.05, 1.0), RATE)
    coeffs.a, coeffs.mean = np.array([0.8, 1.1, 0.6]), np.array([0.1, -0.1, 0.7])
    r = np.array([0.3, 0.2, 0.9])
    lin = ResidualLinearisation(np.tile(r, (3, 1)), np.ones((3, 3, 6)), np.ones((3, 3, 3)))
    offset = np.array([0.05, -0.02, 0.19])
    above = coeffs.linearisation(lin, offset, vertical_acts=True)
    low = coeffs.linearisation(lin, offset, vertical_acts=True, model_vertical=True)
    assert np.array_equal(low.c[:, :2], above.c[:, :2]) and np.array_equal(low.jx[:, :2], above.jx[:, :2])
    assert low.c[0, 2] == pytest.approx(0.9)  # the model's residual, its mean included, no held offset
    assert np.allclose(low.jx[:, 2], 1.0)  # unweighted
    assert low.ju[0, 2, 2] == 0.0  # the thrust scale still owns the thrust's effectiveness
    assert above.c[0, 2] == pytest.approx(0.6 * (0.9 - 0.7) + 0.19)  # above the floor: as before
    assert np.array_equal(coeffs.a, [0.8, 1.1, 0.6]) and np.array_equal(offset, [0.05, -0.02, 0.19])  # untouched


def tick(t: float, frozen: bool, z: float = 0.06) -> SimpleNamespace:
    est = SimpleNamespace(p=np.array([0.0, 0.0, z]), v=np.zeros(3))
    layer = SimpleNamespace(stepping=False, thrust_scale=1.0, frozen=frozen)
    return SimpleNamespace(t=t, est=est, acc=np.zeros(3), source="mpc", model_version=0, compute_s=0.0,
                           saturated=False, layer=layer)


def test_the_recorder_counts_the_ticks_the_layer_held() -> None:
    rec = WindowRecorder(t_col=0.5, rate_hz=RATE, ground_z=0.0, min_height=0.02)
    for k in range(100):
        rec.add(tick(k / RATE, frozen=k >= 60))
    assert rec.held_share(59.5 / RATE) == pytest.approx(40 / 40)
    assert rec.held_share(19.5 / RATE) == pytest.approx(40 / 80)
    assert rec.held_share(1.0) == 0.0  # no tick after it
    # A layer frozen high above the floor (a stale pose) is not the floor's hold.
    rec = WindowRecorder(t_col=0.5, rate_hz=RATE, ground_z=0.0)
    for k in range(100):
        rec.add(tick(k / RATE, frozen=True, z=1.0))
    assert rec.held_share(0.0) == 0.0


def test_a_ground_effect_constant_is_refused_beside_a_measuring_layer_and_judged_with_constants_where_it_holds() -> None:
    lift = np.array([0.0, 0.0, 0.8])  # m/s^2: the ground effect at a steady height, a constant there
    t, x, u = flown_data(lift, n=400, seed=3)
    fresh = gate_pairs(t[200:], x[200:], u[200:], 8.0)
    mf, model = constant_model((0.0, 0.0, 0.8))
    beside = dataclasses.replace(limits(), constant_free=True, steps=5, min_improvement=0.02, min_gain=0.01,
                                 layer_hz=LAYER_HZ)
    # Beside a layer that measures, the constant is the layer's: the model explains nothing the layer leaves.
    assert not run_gate(mf, model, None, fresh, x[:200], u[:200], beside).accepted
    # Where the layer held (near the floor) nothing removed the constant: judged with it, the model flies.
    held = limits()
    verdict = run_gate(mf, model, None, fresh, x[:200], u[:200], held)
    assert verdict.accepted, verdict.reason
    assert verdict.rmse_candidate < 0.5 * verdict.rmse_current
