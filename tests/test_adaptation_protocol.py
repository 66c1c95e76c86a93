"""The controller's adaptation slot: every layer fills the protocol, and the do-nothing one flies the model alone."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.flight.adaptation import AdaptationLayer, LoopAdaptation, NoAdaptation, OracleAdaptation
from cfknode.flight.controller import Controller
from cfknode.flight.estimator import StateEstimate
from cfknode.flight.trajectory import Circle
from cfknode.kernel.setpoint import read_setpoint


def test_every_layer_fills_the_controllers_slot() -> None:
    cfg = load_config()
    layers = (LoopAdaptation(cfg.controller, cfg.vehicle, 0.0),
              OracleAdaptation(cfg.controller, cfg.vehicle, lambda: cfg.vehicle.mass),
              NoAdaptation(cfg.controller, cfg.vehicle))
    assert all(isinstance(layer, AdaptationLayer) for layer in layers)


def test_a_layer_of_ones_own_that_lacks_part_of_the_slot_is_refused_before_the_flight() -> None:
    cfg = load_config()
    layer = NoAdaptation(cfg.controller, cfg.vehicle)
    names = [n for n in dir(AdaptationLayer) if not n.startswith("_") and n != "needs_sample_now"]
    older = SimpleNamespace(**{n: getattr(layer, n) for n in names})  # a layer written before that question
    with pytest.raises(TypeError, match="is not an AdaptationLayer: it lacks needs_sample_now"):
        Controller(cfg.controller, cfg.vehicle, ground_z=0.0, adaptation=older)  # type: ignore[arg-type]
    Controller(cfg.controller, cfg.vehicle, ground_z=0.0, adaptation=layer)


def _fly(adaptation: str, layer: AdaptationLayer | None, seconds: float = 1.0) -> tuple[np.ndarray, list]:
    """A point mass the model matches, on the setpoint's thrust and attitude; the commands and the layer's states."""
    cfg = load_config()
    ctrl = dataclasses.replace(cfg.controller, codegen=False, adaptation=adaptation)
    vehicle, dt = cfg.vehicle, 1.0 / ctrl.rate_hz
    controller = Controller(ctrl, vehicle, ground_z=0.0, adaptation=layer)
    circle = Circle(radius=0.5, speed=0.4, height=1.0)
    start = circle.sample(np.zeros(1))
    p, v, q = start.p[0].copy(), start.v[0].copy(), np.array([1.0, 0.0, 0.0, 0.0])
    accs, states = [], []
    for k in range(int(seconds / dt)):
        t = k * dt
        command = controller.step(t, StateEstimate(t, p, v, q, 0.0), circle)
        accs.append(command.acc)
        states.append(command.layer)
        target = read_setpoint(command.setpoint, vehicle, 0.0, dt)
        q = np.array(target.quaternion)
        body_z = np.array([2 * (q[1] * q[3] + q[0] * q[2]), 2 * (q[2] * q[3] - q[0] * q[1]),
                           1 - 2 * (q[1] ** 2 + q[2] ** 2)])
        v = v + dt * (target.thrust_n / vehicle.mass * body_z - [0.0, 0.0, vehicle.gravity])
        p = p + dt * v
    return np.array(accs), states


def test_no_adaptation_flies_exactly_as_a_layer_that_acts_on_no_axis() -> None:
    cfg = load_config()
    layered, states = _fly("dob", None)
    assert not any(any(s.acts) for s in states)  # the model matches the plant: the layer never acts
    quiet, neutral = _fly("dob", NoAdaptation(cfg.controller, cfg.vehicle))
    np.testing.assert_array_equal(quiet, layered)
    assert all(s.thrust_scale == 1.0 and not s.stepping and not any(s.offset) for s in neutral)
