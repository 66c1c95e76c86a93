"""The learned model and the fast layer as one estimator (flight/adaptation/composite.py).

The fit's math on its own, then the layer in the loop (``LoopAdaptation``, its real wiring: the observer told
the model's weighted prediction, the MPC's residual scaled per axis, the model's vertical mean handed to the
thrust scale) around a point mass on a circle. A proportional-derivative law stands in for the MPC and
cancels the residual the layer hands it, so its error is what the residual gets wrong.
"""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Callable

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.flight.adaptation import LoopAdaptation
from cfknode.flight.adaptation.composite import (
    AxisFit, ModelCoefficients, CoefficientSettings, composite_prediction, fit_coefficient, fit_step, prior_fit,
)
from cfknode.flight.mellinger import CommandShaping, shape_force
from cfknode.flight.mpc_problem import ResidualLinearisation

G = 9.81
RATE = 400.0
DRAG = np.array([0.6, 0.6, 0.3])  # N/(m/s) per kg: the plant's speed-dependent force is -DRAG v
RADIUS, SPEED, HEIGHT = 0.5, 1.0, 1.0


def fit_on(phi: np.ndarray, y: np.ndarray, prior_info: float, keep: float = 0.999) -> float:
    fit: AxisFit = prior_fit(prior_info)
    for p, t in zip(phi.tolist(), y.tolist()):
        fit = fit_step(fit, p, t, keep, prior_info)
    return fit_coefficient(fit, (0.0, 1.5))


def test_the_fit_finds_the_features_weight_beside_a_constant_and_keeps_the_prior_without_excitation() -> None:
    t = np.arange(4000) / RATE
    phi = 0.3 * np.sin(2.0 * math.pi * 0.4 * t)
    assert fit_on(phi, 1.3 * phi + 0.7, prior_info=1.0) == pytest.approx(1.3, abs=0.01)  # the constant is not a's
    assert fit_on(phi, 0.0 * phi - 0.2, prior_info=1.0) < 0.03  # a wrong feature: off (the prior keeps 2 %)
    assert fit_on(np.full_like(t, 0.3), np.full_like(t, 0.9), prior_info=1.0) == pytest.approx(1.0, abs=1e-6)
    assert fit_on(phi, 3.0 * phi, prior_info=1.0) == 1.5  # bounded
    # The prior has constant weight: a feature far below its level barely moves a, however long the flight.
    assert fit_on(0.005 * np.sin(t), 0.0 * t, prior_info=0.05**2 / (1 - 0.999)) > 0.9


def test_the_prediction_weights_the_variation_and_hands_the_vertical_mean_over() -> None:
    r, a, m = np.array([0.5, -0.2, -2.0]), np.array([0.5, 1.0, 1.2]), np.array([0.3, -0.2, -2.1])
    assert np.allclose(composite_prediction(r, a, m), [0.5 * 0.2 + 0.3, -0.2, 1.2 * 0.1])
    coeffs = ModelCoefficients(CoefficientSettings((0.0, 1.5), 4.0, 0.05, 1.0), RATE)
    coeffs.a, coeffs.mean = a, m
    lin = ResidualLinearisation(np.tile(r, (3, 1)), np.ones((3, 3, 6)), np.ones((3, 3, 3)))
    acting = coeffs.linearisation(lin, np.array([0.1, 0.0, 0.05]), vertical_acts=True)
    assert np.allclose(acting.c[0], composite_prediction(r, a, m) + [0.1, 0.0, 0.05])
    assert np.allclose(acting.jx[0, :, 0], a) and np.allclose(acting.ju[1, :2, 2], a[:2])
    assert acting.ju[1, 2, 2] == 0.0  # the thrust's effectiveness is the thrust scale's
    # While the vertical does not act its slope in u_z flies, but its mean still does not: the MPC flies what
    # the observer was told, so a constant the layer never saw cannot fly behind its back.
    idle = coeffs.linearisation(lin, np.zeros(3), vertical_acts=False)
    assert idle.c[0, 2] == pytest.approx(1.2 * 0.1) and idle.ju[1, 2, 2] == pytest.approx(1.2)
    assert np.allclose(idle.c[0], coeffs.prediction(r))


def test_the_mean_is_taken_again_on_the_first_steady_tick_after_the_climb() -> None:
    """On the take-off's climb a model's output is also the ground effect and the inflow: the mean taken there
    (so that a model's mass reaches the thrust scale before the pattern) is taken again, at once, on the first
    steady tick, where the model is; the prediction stays continuous through the observer (the shift), and the
    filtered feature starts again with it. A swap's mean (the recent ticks', not one tick's) is kept, on the climb
    too; a new take-off climbs again."""
    settings = CoefficientSettings((0.0, 1.5), 4.0, 0.05, 4.0)
    coeffs = ModelCoefficients(settings, RATE)
    sigma, omega = np.zeros(3), np.full(3, 2.0 * math.pi)
    climb = np.array([0.0, 0.0, 0.9])  # the ground effect's lift near the floor
    coeffs.tick(climb, sigma, omega, 1.0 / RATE, learn=False, steady=False)
    assert np.allclose(coeffs.mean, climb)  # the first tick's, as before
    for _ in range(200):
        coeffs.tick(climb + [0.0, 0.0, -0.5], sigma, omega, 1.0 / RATE, learn=False, steady=False)
    assert 0.7 < coeffs.mean[2] < 0.9  # slowly, on the climb
    cruise = np.array([0.1, -0.05, -0.3])  # the model where it tracks
    m_old = coeffs.mean.copy()
    shift = coeffs.tick(cruise, sigma, omega, 1.0 / RATE, learn=False, steady=True)
    assert np.allclose(coeffs.mean, cruise)  # taken at once: nothing of the climb left in it
    assert shift[2] == pytest.approx(cruise[2] - m_old[2])  # handed to the observer's estimate
    assert np.allclose(coeffs._phi_f, 0.0, atol=1e-9)  # the feature r - m is 0, and so is its filtered value
    coeffs.tick(climb, sigma, omega, 1.0 / RATE, learn=False, steady=True)
    assert coeffs.mean[2] == pytest.approx(-0.3 + (0.9 + 0.3) / (4.0 * RATE))  # then slowly again
    coeffs.restart(np.tile(cruise, (5, 1)))  # a swap: its mean is where the vehicle flew, and stays
    coeffs.tick(climb, sigma, omega, 1.0 / RATE, learn=False, steady=True)
    assert coeffs.mean[2] == pytest.approx(-0.3 + (0.9 + 0.3) / (4.0 * RATE))
    coeffs.reset()
    coeffs.restart(np.tile(climb, (5, 1)))  # a swap on the climb: its mean is the recent ticks', not taken again
    coeffs.tick(cruise, sigma, omega, 1.0 / RATE, learn=False, steady=True)
    assert coeffs.mean[2] == pytest.approx(0.9 + (-0.3 - 0.9) / (4.0 * RATE))
    coeffs.reset()  # landed: the next take-off climbs again
    coeffs.tick(climb, sigma, omega, 1.0 / RATE, learn=False, steady=False)
    coeffs.tick(cruise, sigma, omega, 1.0 / RATE, learn=False, steady=True)
    assert np.allclose(coeffs.mean, cruise)


def test_a_swapped_in_constant_the_layer_already_holds_stays_the_layers() -> None:
    """At a swap, a network whose horizontal mean is near the layer's own offset there learned the constant the
    layer has (a wind): the layer keeps it (k = 0) and the network flies its variation about that mean, which is
    held; a mean the layer did not hold (a network fitted on the take-off) flies as the network's."""
    coeffs = ModelCoefficients(CoefficientSettings((0.0, 1.5), 4.0, 0.05, 1.0), RATE)
    recent = np.tile([0.35, 0.18, 0.05], (40, 1))
    coeffs.restart(recent, layer_offset=np.array([0.46, 0.0, 0.02]))  # x: 0.76 of the layer's; y: the layer had none
    r = np.array([0.40, 0.20, 0.05])
    # x: only the variation about the held mean (the layer's offset carries the 0.35); y: the network's mean too.
    assert np.allclose(coeffs.prediction(r), [0.05, 0.20, 0.0])
    sigma, omega, held = np.zeros(3), np.full(3, 2.0 * math.pi), float(coeffs.mean[0])
    for _ in range(400):
        coeffs.tick(r, sigma, omega, 1.0 / RATE, learn=False)
    assert coeffs.mean[0] == held and coeffs.mean[1] > 0.19  # held on x; y follows the network's output
    lin = ResidualLinearisation(np.tile(r, (2, 1)), np.zeros((2, 3, 6)), np.zeros((2, 3, 3)))
    flown = coeffs.linearisation(lin, np.array([0.46, 0.0, 0.0]), vertical_acts=True)
    assert flown.c[0, 0] == pytest.approx(0.46 + 0.05)  # the layer's constant and the network's variation
    for offset in ([0.46, 0.0, 0.0], [-0.3, 0.18, 0.0], [0.2, 0.0, 0.0]):  # far from the mean, or the other sign
        other = ModelCoefficients(CoefficientSettings((0.0, 1.5), 4.0, 0.05, 1.0), RATE, (False, True, True))
        other.restart(recent, (False, True, True), np.array(offset))
        assert other.prediction(r)[0] == 0.0  # an axis the network does not fly stays the layer's alone
    far = ModelCoefficients(CoefficientSettings((0.0, 1.5), 4.0, 0.05, 1.0), RATE)
    far.restart(recent, layer_offset=np.array([0.9, -0.2, 0.0]))  # x: 0.39 of the layer's; y: the other sign
    assert np.allclose(far.prediction(r)[:2], [0.40, 0.20])
    none = ModelCoefficients(CoefficientSettings((0.0, 1.5), 4.0, 0.05, 1.0), RATE)
    none.restart(np.zeros((40, 3)), layer_offset=np.zeros(3))  # no offset, no mean: nothing the layer holds
    none.tick(r, sigma, omega, 1.0 / RATE, learn=False)
    assert none.mean[0] > 0.0  # the mean moves, as a network's own


class SpeedModel:
    """A learned model that explains ``share`` of the plant's drag (and, optionally, a constant)."""

    def __init__(self, share: float, constant: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        self.share, self.constant = share, np.array(constant)

    def evaluate(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return -self.share * DRAG * np.atleast_2d(x)[:, 3:6] + self.constant if np.ndim(x) == 2 else \
            -self.share * DRAG * x[3:6] + self.constant

    def linearise(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = x.shape[0]
        jx = np.zeros((n, 3, 6))
        jx[:, [0, 1, 2], [3, 4, 5]] = -self.share * DRAG
        return np.tile(self.constant, (n, 1)), jx, np.zeros((n, 3, 3))


def quaternion_to(direction: np.ndarray) -> np.ndarray:
    """(w, x, y, z) turning e_z onto ``direction``: the attitude loop here is instant."""
    d = direction / np.linalg.norm(direction)
    w = math.sqrt(max(0.5 * (1.0 + d[2]), 1e-12))
    return np.array([w, -d[1] / (2 * w), d[0] / (2 * w), 0.0])


def fly(model: SpeedModel | None, layer: bool, seconds: float = 12.0,
        mass: Callable[[float], float] = lambda t: 1.0, wind: np.ndarray = np.zeros(3)) -> SimpleNamespace:
    """The circle with the plant's drag, ``wind`` and the mass ``mass(t)`` x nominal; returns the position RMS
    error over the last 4 s, the coefficients and the layer's estimate at the end."""
    # The plant's thrust acts at once: the layer is told so (a motor lag it assumed would show as an error
    # proportional to the circle's jerk, i.e. to the velocity, which the speed feature's weight would take).
    cfg = load_config(overrides={"controller.adaptation": "dob", "controller.adaptation_settings.thrust_lag_s": 0.001})
    ctrl, veh = cfg.controller, cfg.vehicle
    adapt = LoopAdaptation(ctrl, veh, ground_z=0.0) if layer else None
    slot = SimpleNamespace(version=1, model=model) if model is not None else None
    dt, w = 1.0 / RATE, SPEED / RADIUS
    p, v, u_prev = np.array([RADIUS, 0.0, HEIGHT]), np.array([0.0, SPEED, 0.0]), np.zeros(3)
    q, errors = np.array([1.0, 0.0, 0.0, 0.0]), []
    for i in range(int(seconds * RATE)):
        t = i * dt
        c, s = math.cos(w * t), math.sin(w * t)
        p_ref = np.array([RADIUS * c, RADIUS * s, HEIGHT + 0.1 * math.sin(1.3 * t)])
        v_ref = np.array([-SPEED * s, SPEED * c, 0.13 * math.cos(1.3 * t)])
        a_ref = np.array([-SPEED * w * c, -SPEED * w * s, -0.169 * math.sin(1.3 * t)])
        if t > seconds - 4.0:
            errors.append(p - p_ref)
        x = np.concatenate((p, v))
        raw = ResidualLinearisation(*model.linearise(x[None, :], u_prev[None, :])) if model is not None else None
        lin = raw
        shaping = None
        if adapt is not None:
            adapt.before_solve(t, SimpleNamespace(p=p, v=v, q=q, t=t), True, "TRACK", slot)
            lin = adapt.residual(lin, 1)
            shaping = adapt.shaping()
        residual = np.zeros(3) if lin is None else lin.c[0] + lin.jx[0] @ x + lin.ju[0] @ u_prev
        u = a_ref + 16.0 * (p_ref - p) + 8.0 * (v_ref - v) - residual
        shaped = shape_force(u, veh, ctrl, shaping or CommandShaping())
        thrust_cmd = int(round(np.linalg.norm(shaped.force) / veh.newton_per_cmd))
        if adapt is not None:
            adapt.after_command(x, shaped, thrust_cmd, raw)
        force = np.asarray(shaped.force) * (thrust_cmd * veh.newton_per_cmd / np.linalg.norm(shaped.force))
        q = quaternion_to(force)
        v = v + dt * (force / (veh.mass * mass(t)) - np.array([0.0, 0.0, G]) - DRAG * v + wind)
        p = p + dt * v
        u_prev = np.asarray(shaped.applied_acc)
    coeffs = adapt.coefficients if adapt is not None else None
    return SimpleNamespace(rms=float(np.sqrt(np.mean(np.square(errors)))), axes=np.sqrt(np.mean(np.square(errors), axis=0)), adapt=adapt,
                           a=None if coeffs is None else coeffs.a.copy(),
                           estimate=None if adapt is None else adapt.layer.estimate)


@pytest.fixture(scope="module")
def alone() -> SimpleNamespace:
    """The layer alone and the model alone (it explains 70 % of the drag) on the circle."""
    return SimpleNamespace(layer=fly(None, True), model=fly(SpeedModel(0.7), False))


def test_a_model_that_explains_the_speed_force_keeps_its_weight_and_the_layer_its_offset_small(
        alone: SimpleNamespace) -> None:
    both = fly(SpeedModel(1.0), True)
    assert np.allclose(both.a, 1.0, atol=0.1)
    assert np.abs(both.estimate.offset).max() < 0.05
    # Within 0.3 mm of the better one: the layer reads 1-2 % more speed force than there is (its motor-lag
    # model on an instant plant), which the weight takes.
    assert both.rms <= min(alone.layer.rms, fly(SpeedModel(1.0), False).rms) + 3e-4


def test_a_model_that_explains_part_of_the_force_is_weighted_up_and_beats_either_alone(
        alone: SimpleNamespace) -> None:
    both = fly(SpeedModel(0.7), True)
    assert both.a[0] == pytest.approx(1.0 / 0.7, abs=0.12) and both.a[1] == pytest.approx(1.0 / 0.7, abs=0.12)
    assert both.rms < 0.8 * min(alone.layer.rms, alone.model.rms)


def test_a_mass_step_goes_to_the_thrust_scale_and_a_wind_to_the_offset_with_the_model_flying() -> None:
    both = fly(SpeedModel(1.0), True, mass=lambda t: 1.0 if t < 5.0 else 1.3, wind=np.array([0.5, 0.0, 0.0]))
    assert both.estimate.thrust_scale == pytest.approx(1.3, abs=0.03)
    assert both.estimate.offset[0] == pytest.approx(0.5, abs=0.06)
    assert np.allclose(both.a, 1.0, atol=0.15)  # neither the mass nor the wind is the model's
    assert both.rms < 0.01


def test_a_wrong_vertical_constant_below_the_layers_level_is_not_flown() -> None:
    """A network fitted on a transient carries a small vertical constant the plant does not have, below the level
    at which the layer's vertical acts. It is handed to the layer with the rest of the model's mean, where the
    observer sees nothing to explain, so it flies nowhere: z is as with the same model without the constant
    (flown as the model's it held the vehicle low, 1.2-1.9 mm RMS against 0.12)."""
    good = fly(SpeedModel(1.0), True)
    for constant in (0.02, -0.03):
        wrong = fly(SpeedModel(1.0, constant=(0.0, 0.0, constant)), True)
        assert wrong.axes[2] <= good.axes[2] + 5e-5 and wrong.axes[2] < 5e-4


def test_a_model_that_carries_the_mass_hands_it_to_the_thrust_scale() -> None:
    """The offline case: a model trained on the heavy vehicle predicts its missing lift as a constant. The
    layer's thrust scale takes it (so the MPC is not told to hold a standing input), the model keeps its
    weight, and the flight is the layer's alone or better."""
    carries = SpeedModel(1.0, constant=(0.0, 0.0, -G * 0.3 / 1.3))
    both = fly(carries, True, mass=lambda t: 1.3)
    assert both.estimate.thrust_scale == pytest.approx(1.3, abs=0.03)
    assert both.adapt.coefficients.mean[2] == pytest.approx(-G * 0.3 / 1.3, abs=0.1)
    assert both.rms <= 1.05 * fly(None, True, mass=lambda t: 1.3).rms
