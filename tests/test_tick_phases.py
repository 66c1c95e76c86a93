"""A tick in two phases: the work that waits for no new pose is done after the send."""

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
from cfknode.kernel.imu import ImuSample
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


@dataclasses.dataclass
class Flight:
    acc: np.ndarray  # (ticks, 3) commanded accelerations
    thrust: np.ndarray  # (ticks,) thrust commands
    linearised: dict[str, int]  # the model's linearisations per phase ("step", "prepare")
    learned: dict[str, int]  # the layer's updates from a pose (before_solve) per phase
    flown: list[Any]  # the layer's estimate each command flew (Command.layer)
    after_prepare: list[Any]  # the layer's estimate after each preparation (split only)
    rebases: list[int]  # the layer's re-bases after each step
    inside: list[int]  # the ticks whose pose the layer learned inside the step


def _fly(split: bool, seconds: float = 0.6, swap_at: int | None = None, imu_every: int = 0,
         mass_step: tuple[int, float] | None = None, accel_hz: float = 0.0) -> Flight:
    """A point mass 1.2x heavier than the controller believes, flown with the layer and a three-network queue;
    ``split``: the controller is told its caller prepares after each send, and it does. ``swap_at``: the tick
    before which another queue swaps in (after the previous tick's preparation). ``imu_every``: an
    accelerometer sample (the specific force the thrust gives) every that many ticks (0: none). ``mass_step``:
    (tick, factor): from that tick the mass is ``factor`` times the believed one. ``accel_hz``: the accelerometer's
    fast path's cut-off (0: off, the default)."""
    cfg = load_config()
    ctrl = dataclasses.replace(cfg.controller, codegen=False, adaptation="dob", adaptation_settings=dataclasses.replace(
        cfg.controller.adaptation_settings, accel_cutoff_hz=accel_hz))
    vehicle, dt = cfg.vehicle, 1.0 / ctrl.rate_hz
    counts: dict[str, int] = {}
    learned: dict[str, int] = {}
    phase = ["step"]
    tick = [0]
    inside: list[int] = []
    queues = [CountingModel(synthetic_queue(cfg.knode.hidden, 3, seed=s), counts, phase) for s in (1, 2)]
    slot = ModelSlot(queues[0], version=1)
    controller = Controller(ctrl, vehicle, model=slot, ground_z=0.0)
    controller.prepares_after_send = split
    layer = controller.adaptation
    before_solve = layer.before_solve  # type: ignore[union-attr]

    def counted(*args: Any) -> Any:
        learned[phase[0]] = learned.get(phase[0], 0) + 1
        if phase[0] == "step":
            inside.append(tick[0])
        return before_solve(*args)

    layer.before_solve = counted  # type: ignore[union-attr]
    circle = Circle(radius=0.5, speed=0.4, height=1.0)
    start = circle.sample(np.zeros(1))
    p, v, q = start.p[0].copy(), start.v[0].copy(), np.array([1.0, 0.0, 0.0, 0.0])
    imu = None
    out = Flight([], [], counts, learned, [], [], [], inside)
    mass, specific_force = 1.2 * vehicle.mass, vehicle.gravity
    for k in range(int(round(seconds / dt))):
        t, tick[0] = k * dt, k
        if mass_step is not None and k == mass_step[0]:
            mass = mass_step[1] * vehicle.mass
        if k == swap_at:
            slot.swap(queues[1], version=2, now=t)
        phase[0] = "step"
        if imu_every and k % imu_every == 0:
            imu = ImuSample(t, np.array([0.0, 0.0, specific_force]))
        command = controller.step(t, StateEstimate(t, p, v, q, 0.0, imu=imu), circle)
        out.acc.append(command.acc)
        out.thrust.append(command.setpoint.thrust)
        out.flown.append(command.layer)
        out.rebases.append(layer.layer.rebases)  # type: ignore[union-attr]
        if split:
            phase[0] = "prepare"
            controller.prepare()
            out.after_prepare.append(layer.estimate)  # type: ignore[union-attr]
        target = read_setpoint(command.setpoint, vehicle, 0.0, dt)
        q = np.array(target.quaternion)
        body_z = np.array([2 * (q[1] * q[3] + q[0] * q[2]), 2 * (q[2] * q[3] - q[0] * q[1]),
                           1 - 2 * (q[1] ** 2 + q[2] ** 2)])
        specific_force = target.thrust_n / mass
        v = v + dt * (specific_force * body_z - [0.0, 0.0, vehicle.gravity])
        p = p + dt * v
    out.acc, out.thrust = np.array(out.acc), np.array(out.thrust)
    return out


def test_a_split_tick_learns_after_the_send_and_flies_the_estimate_from_the_pose_before() -> None:
    ticks = 240
    together, split = _fly(split=False), _fly(split=True)
    assert together.linearised == {"step": ticks} and together.learned == {"step": ticks}
    # Only the first tick, with no plan and no layer update yet, linearises and learns inside the step.
    assert split.linearised == {"step": 1, "prepare": ticks}
    assert split.learned == {"step": 1, "prepare": ticks - 1}
    # Each command flies the estimate the last preparation left: learned from the pose one tick before.
    assert all(flown is prepared for flown, prepared in zip(split.flown[1:], split.after_prepare[:-1]))
    # ... which flies almost the same: the layer moves little in 2.5 ms. The mass step is learned a tick later
    # (up to 0.1 m/s^2 apart for a tick or two); from then on the commands are within 0.01 m/s^2.
    assert not np.array_equal(split.acc, together.acc)
    np.testing.assert_allclose(split.acc, together.acc, atol=0.1)
    np.testing.assert_allclose(split.acc[40:], together.acc[40:], atol=0.01)
    assert np.max(np.abs(split.thrust - together.thrust)) <= 0.01 * np.max(together.thrust)


def test_a_quiet_accelerometer_sample_waits_for_the_send_and_a_step_it_shows_does_not() -> None:
    """A sample that raises no alarm only teaches the step detector its noise: it is learned after the send. A
    sample that shows a step acts on its own tick's command, and so do the samples while the step is tracked."""
    every, step = 4, 600
    split = _fly(split=True, seconds=2.0, imu_every=every, mass_step=(step, 1.6))
    together = _fly(split=False, seconds=2.0, imu_every=every, mass_step=(step, 1.6))
    inside = np.array(split.inside)
    assert inside[0] == 0  # the first tick: nothing learned before it
    quiet = inside[(inside > 0) & (inside < step)]
    assert quiet.size == 0, quiet  # 150 samples before the step, none learned inside
    shown = inside[inside >= step]
    assert shown.size and shown[0] <= step + 2 * every  # the step's first or second sample raised the alarm
    assert all(k % every == 0 for k in shown)  # only ticks with a sample: between them the layer learns after
    # The tick whose command first flies the step's mass is the same as learning every pose inside gives.
    scale = np.array([e.thrust_scale for e in together.flown])
    first = step + int(np.argmax(scale[step:] > scale[step - 1] + 0.1))
    assert first in shown
    assert abs(split.flown[first].thrust_scale - scale[first]) < 0.01
    assert split.flown[first - 1].thrust_scale < scale[step - 1] + 0.1


def test_with_the_accelerometer_s_fast_path_every_sample_is_learned_inside() -> None:
    """The fast path adds each sample's residual to this tick's offset: no sample waits for the send."""
    split = _fly(split=True, seconds=0.4, imu_every=4, accel_hz=2.0)
    assert split.inside == list(range(0, 160, 4))


def test_a_swap_after_the_preparation_is_learned_beside_inside_the_tick() -> None:
    ticks, swap = 240, 120
    split = _fly(split=True, swap_at=swap)
    # Inside the steps: the first tick's linearisation; the layer's re-base on the swap (the new model at the
    # recent ticks); and the new model at the swap's tick, whose preparation was done for the old one.
    assert split.linearised == {"step": 3, "prepare": ticks}
    # The swap's tick learns inside: the layer re-bases on the new model before the solve flies it.
    assert split.learned == {"step": 2, "prepare": ticks - 2}
    assert split.rebases[swap] == split.rebases[swap - 1] + 1
    unswapped = _fly(split=True)
    assert np.array_equal(unswapped.acc[:swap], split.acc[:swap])
    assert not np.array_equal(unswapped.acc[swap:], split.acc[swap:])  # the swap did change what flew


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
