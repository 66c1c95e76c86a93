"""A tick in two phases: the work that needs no new pose done after the send flies the same commands."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from typing import Any

import numpy as np

from cfknode.app.bench.timing import synthetic_queue
from cfknode.app.config import load_config
from cfknode.flight.controller import Controller
from cfknode.flight.estimator import StateEstimate
from cfknode.flight.model_slot import ModelSlot
from cfknode.flight.trajectory import Circle
from cfknode.kernel.setpoint import read_setpoint


class CountingModel:
    """A residual queue whose linearisations are counted, and told apart by where they were asked for."""

    def __init__(self, inner: Any, counts: dict[str, int], phase: list[str]) -> None:
        self.inner, self.counts, self.phase = inner, counts, phase
        self.takes_neighbour = False

    def linearise(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        self.counts[self.phase[0]] = self.counts.get(self.phase[0], 0) + 1
        return self.inner.linearise(x, u)

    def evaluate(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.inner.evaluate(x, u)


def _fly(split: bool, seconds: float = 0.6, swap_at: int | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """A point mass 1.2x heavier than the controller believes, flown with the layer and a three-network queue;
    ``split``: the controller is told its caller prepares after each send, and it does. ``swap_at``: the tick
    before which another queue swaps in (after the previous tick's preparation). Returns the accelerations,
    the thrust commands, and the linearisations counted per phase."""
    cfg = load_config()
    ctrl = dataclasses.replace(cfg.controller, codegen=False, adaptation="dob")
    vehicle, dt = cfg.vehicle, 1.0 / ctrl.rate_hz
    counts: dict[str, int] = {}
    phase = ["step"]
    queues = [CountingModel(synthetic_queue(cfg.knode.hidden, 3, seed=s), counts, phase) for s in (1, 2)]
    slot = ModelSlot(queues[0], version=1)
    controller = Controller(ctrl, vehicle, model=slot, ground_z=0.0)
    controller.prepares_after_send = split
    circle = Circle(radius=0.5, speed=0.4, height=1.0)
    start = circle.sample(np.zeros(1))
    p, v, q = start.p[0].copy(), start.v[0].copy(), np.array([1.0, 0.0, 0.0, 0.0])
    accs, thrusts = [], []
    for k in range(int(round(seconds / dt))):
        t = k * dt
        if k == swap_at:
            slot.swap(queues[1], version=2, now=t)
        phase[0] = "step"
        command = controller.step(t, StateEstimate(t, p, v, q, 0.0), circle)
        accs.append(command.acc)
        thrusts.append(command.setpoint.thrust)
        if split:
            phase[0] = "prepare"
            controller.prepare()
        target = read_setpoint(command.setpoint, vehicle, 0.0, dt)
        q = np.array(target.quaternion)
        body_z = np.array([2 * (q[1] * q[3] + q[0] * q[2]), 2 * (q[2] * q[3] - q[0] * q[1]),
                           1 - 2 * (q[1] ** 2 + q[2] ** 2)])
        v = v + dt * (target.thrust_n / (1.2 * vehicle.mass) * body_z - [0.0, 0.0, vehicle.gravity])
        p = p + dt * v
    return np.array(accs), np.array(thrusts), counts


def test_a_tick_prepared_after_the_send_flies_the_same_commands_and_linearises_there() -> None:
    ticks = 240
    together, thrust_together, counts_together = _fly(split=False)
    split, thrust_split, counts_split = _fly(split=True)
    np.testing.assert_array_equal(split, together)
    np.testing.assert_array_equal(thrust_split, thrust_together)
    assert counts_together == {"step": ticks}
    # Only the first tick, with no plan yet, linearises inside the step; the last preparation goes unused.
    assert counts_split == {"step": 1, "prepare": ticks}


def test_a_swap_after_the_preparation_flies_the_new_model_at_once() -> None:
    ticks, swap = 240, 120
    together, _, _ = _fly(split=False, swap_at=swap)
    split, _, counts = _fly(split=True, swap_at=swap)
    np.testing.assert_array_equal(split, together)
    # Inside the steps: the first tick; the layer's re-base on the swap (the new model at the recent ticks); and
    # the new model at the swap's tick, whose preparation was done for the old one.
    assert counts == {"step": 3, "prepare": ticks}
    unswapped, _, _ = _fly(split=True)
    assert not np.array_equal(unswapped[swap:], split[swap:])  # the swap did change what flew


def test_a_model_given_the_neighbours_moving_position_is_not_linearised_ahead() -> None:
    queue = synthetic_queue((8,), 1)
    slot = ModelSlot(queue, version=1)
    x, u = np.zeros((4, 6)), np.zeros((4, 3))
    prepared = slot.prepare(x, u)
    assert prepared is not None and slot.holds(prepared)
    slot.neighbour = SimpleNamespace(horizon=lambda nodes: None)
    slot.swap(SimpleNamespace(takes_neighbour=True, linearise=queue.linearise), version=2, now=0.0)
    assert slot.prepare(x, u) is None
    assert not slot.holds(prepared)  # the swap ended the one done for the first model
    assert ModelSlot(None).prepare(x, u) is None  # nominal: nothing to linearise


def test_a_command_left_for_the_preparation_reaches_the_layer_before_a_reset() -> None:
    """``idle`` between a step and its preparation: the layer hears of the command first, so the reset that
    follows is the one a layer that had flown it does."""
    cfg = load_config()
    ctrl = dataclasses.replace(cfg.controller, codegen=False, adaptation="dob")
    circle = Circle(radius=0.5, speed=0.4, height=1.0)
    start = circle.sample(np.zeros(1))
    resets = []
    for split in (False, True):
        controller = Controller(ctrl, cfg.vehicle, ground_z=0.0)
        controller.prepares_after_send = split
        state = StateEstimate(0.0, start.p[0].copy(), start.v[0].copy(), np.array([1.0, 0.0, 0.0, 0.0]), 0.0)
        controller.step(0.0, state, circle)
        controller.idle()
        resets.append(controller.adaptation.layer.resets)  # type: ignore[union-attr]
    assert resets == [2, 2]  # the one at construction, and the off-air reset of a layer that had a command
