"""Ticks flown at the thrust clamp never reach the trainer, on every path: with and without the fast layer,
for a Controller embedded through the public API (its own observers) and for the flight loop (``Command``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import pytest

import cfknode
from cfknode.app.learning import learner_settings
from cfknode.flight.learning.learner import OnlineLearner
from cfknode.flight.model_slot import ModelSlot
from cfknode.kernel.setpoint import read_setpoint
from fakes import ListLog
from test_online_learner import ScriptedTrainer, outcome_with

HEIGHT = 1.0
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


@dataclass(frozen=True)
class State:
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray


class Hover:
    """A hover reference at (0, 0, HEIGHT)."""

    def sample(self, t: np.ndarray) -> cfknode.RefSamples:
        n = t.shape[0]
        p = np.tile([0.0, 0.0, HEIGHT], (n, 1))
        return cfknode.RefSamples(t, p, np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n))


def fly(adaptation: str, thrust_to_weight: float | None, seconds: float = 1.6,
        start_below: float = 0.0) -> tuple[OnlineLearner, ScriptedTrainer, int]:
    """A level vehicle whose thrust at the clamp is ``thrust_to_weight`` of its weight (None: the vehicle's own),
    flown by a public-API Controller with an online learner as its observer; returns (learner, trainer, saturated
    ticks). Below 1 it sinks with the thrust at the clamp on every tick; ``start_below`` m under the reference,
    sinking at 0.5 m/s, it is there from the first tick."""
    # No reserve for tilt in the layer's thrust cone: its vertical bound is then the clamp itself (with the
    # reserve it stops 0.4 % short of it, and the command flies uncut).
    cfg = cfknode.load_config(overrides={"controller.adaptation": adaptation, "online.enabled": True,
                                         "controller.cone_reserve_deg": 0.0})
    vehicle = cfg.vehicle
    ctrl = cfknode.Controller(cfg.controller, vehicle, model=ModelSlot(None, version=0), ground_z=-10.0)
    trainer = ScriptedTrainer(lambda request: outcome_with(None, request))
    settings = replace(learner_settings(cfg, lockstep=False), filter_hz=0.0)
    learner = OnlineLearner(settings, ctrl.model, trainer, ListLog())
    ctrl.observers.append(learner)
    # Thrust at the clamp over weight of the vehicle config; the plant's mass makes it ``thrust_to_weight``.
    clamp_tw = vehicle.thrust_cmd_clamp * vehicle.newton_per_cmd / (vehicle.mass * vehicle.gravity)
    mass = vehicle.mass if thrust_to_weight is None else vehicle.mass * clamp_tw / thrust_to_weight
    period = 1.0 / cfg.controller.rate_hz
    p, v = np.array([0.0, 0.0, HEIGHT - start_below]), np.array([0.0, 0.0, -0.5 if start_below else 0.0])
    saturated = 0
    for k in range(int(round(seconds / period))):
        command = ctrl.step(k * period, State(p.copy(), v.copy(), LEVEL), Hover())
        ctrl.publish()
        saturated += int(command.saturated)
        thrust = read_setpoint(command.setpoint, vehicle, 0.0, period).thrust_n
        a = np.array([0.0, 0.0, thrust / mass - vehicle.gravity])  # level: only the vertical moves
        p, v = p + period * v + 0.5 * period * period * a, v + period * a
    return learner, trainer, saturated


@pytest.mark.parametrize("adaptation", ["none", "dob"])
def test_a_window_flown_at_the_clamp_never_reaches_the_trainer(adaptation: str) -> None:
    learner, trainer, saturated = fly(adaptation, thrust_to_weight=0.97, start_below=0.3)
    assert saturated == int(round(1.6 * 400))  # sinking: the thrust sits at the clamp on every tick
    assert learner.recorder.windows == 0 and trainer.requests == []


@pytest.mark.parametrize("adaptation", ["none", "dob"])
def test_the_same_flight_off_the_clamp_is_trained_on(adaptation: str) -> None:
    # The control: a vehicle that hovers well inside its thrust cuts windows and sends them.
    learner, trainer, saturated = fly(adaptation, thrust_to_weight=None)
    assert saturated == 0
    assert learner.recorder.windows >= 2 and len(trainer.requests) >= 1
    assert all(math.isfinite(float(r.window.u.sum())) for r in trainer.requests)


def test_the_flag_reaches_the_loop_s_observers_from_the_command() -> None:
    # The flight loop builds its observers' TickInfo from Command.saturated (flight/loop.py): the Command of a
    # clamped tick says so without a fast layer too.
    cfg = cfknode.load_config(overrides={"controller.adaptation": "none"})
    ctrl = cfknode.Controller(cfg.controller, cfg.vehicle)
    below = ctrl.step(0.0, State(np.array([0.0, 0.0, HEIGHT - 1.0]), np.array([0.0, 0.0, -1.0]), LEVEL), Hover())
    assert below.setpoint.thrust == cfg.vehicle.thrust_cmd_clamp and below.saturated
    ctrl = cfknode.Controller(cfg.controller, cfg.vehicle)
    at = ctrl.step(0.0, State(np.array([0.0, 0.0, HEIGHT]), np.zeros(3), LEVEL), Hover())
    assert at.setpoint.thrust < cfg.vehicle.thrust_cmd_clamp and not at.saturated
