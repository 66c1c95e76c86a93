"""The fall guard (flight/fall_guard.py): a sudden lost thrust while falling flies the clamp at once, and only then.

The vertical plant here is the simulator's in one dimension: the thrust sent reaches the vehicle through a
first-order lag, and the accelerometer reads the acting thrust over the true mass every 10 ms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

import cfknode
from cfknode.app.bench.thrust_sag import step_sag
from cfknode.flight.fall_guard import (RELEASE_S, RELEASE_SPEED, FallGuard, FallGuardSettings, guard_acceleration, lag_step,
                                       stopping_distance)
from cfknode.kernel.imu import ImuSample
from cfknode.kernel.setpoint import read_setpoint

LEVEL = np.array([1.0, 0.0, 0.0, 0.0])
RATE = 400.0
HEIGHT = 1.5


@dataclass(frozen=True)
class State:
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    imu: ImuSample | None = None


def test_lag_step_is_the_exact_first_order_response() -> None:
    assert lag_step(0.0, 1.0, 0.1, 0.1) == 1.0 - math.exp(-1.0)
    assert lag_step(0.3, 1.0, 0.1, 0.0) == 1.0  # no lag: the command at once


def test_the_guard_command_is_the_whole_clamp_leaning_at_most_the_reserve() -> None:
    vehicle = cfknode.load_config().vehicle
    f_max = vehicle.max_thrust / vehicle.mass
    small = guard_acceleration(np.array([0.3, -0.4, -3.0]), vehicle, 5.0)
    assert small[0] == 0.3 and small[1] == -0.4  # the MPC's horizontal command stays when it fits
    assert math.isclose(math.hypot(0.5, small[2] + vehicle.gravity), f_max)  # the rest of the clamp lifts
    large = guard_acceleration(np.array([1.0, -2.0, -3.0]), vehicle, 5.0)
    assert math.isclose(math.hypot(large[0], large[1]), f_max * math.sin(math.radians(5.0)))
    assert math.isclose(large[1] / large[0], -2.0)  # shrunk along its own direction
    assert math.isclose(math.hypot(math.hypot(large[0], large[1]), large[2] + vehicle.gravity), f_max)


def test_the_stopping_distance_is_the_lag_s_exact_sag() -> None:
    g = 9.81
    # From rest with the thrust at 0.376 of the weight: the sag of a clamp sent at the step (thrust_sag's bound).
    assert math.isclose(stopping_distance(0.0, (0.5 / 1.33 - 1.0) * g, 0.05 * g, 0.1), step_sag(1.05, 0.5, 1.33, 0.1),
                        rel_tol=1e-3)
    assert math.isclose(stopping_distance(1.0, 0.0, 1.5, 0.0), 1.0 / 3.0)  # no lag: v^2 / 2a
    assert stopping_distance(0.5, -1.0, 0.0) == math.inf  # no margin: the fall cannot be stopped
    assert stopping_distance(-0.2, 0.5, 2.0) == 0.0  # rising and lifted: nothing to stop
    assert stopping_distance(1.0, 0.0, 1.5, 0.1) > stopping_distance(1.0, 0.0, 1.5, 0.0)  # the lag only adds


def feed(guard: FallGuard, mass: float, thrust_n: float, seconds: float, t0: float, vz: float,
         measured_thrust: float | None = None, above: float = 0.0) -> list[bool]:
    """Ticks at RATE with ``thrust_n`` sent; the accelerometer (100 Hz) reads ``measured_thrust`` (default the
    sent one) over ``mass``. Returns whether the guard flew each tick."""
    out = []
    for k in range(int(round(seconds * RATE))):
        t = t0 + k / RATE
        f = (thrust_n if measured_thrust is None else measured_thrust) / mass
        imu = ImuSample(math.floor(t * 100.0) / 100.0, np.array([0.0, 0.0, f]))
        out.append(guard.engaged(State(np.array([0.0, 0.0, HEIGHT]), np.array([0.0, 0.0, vz]), LEVEL, imu), 0.0, True,
                                 above))
        guard.sent(thrust_n)
    return out


def make_guard() -> tuple[FallGuard, Any]:
    vehicle = cfknode.load_config().vehicle
    return FallGuard(FallGuardSettings(3.0, 5.0, RATE), vehicle), vehicle


def test_a_lost_thrust_while_falling_engages_within_two_samples_and_a_climb_releases() -> None:
    guard, vehicle = make_guard()
    hover = vehicle.mass * vehicle.gravity
    # Hovering with an offset the guard learns (the vehicle is lighter than the config: a model's or a payload's).
    assert not any(feed(guard, 0.5 * vehicle.mass, 0.5 * hover, 1.0, 0.0, 0.0))
    # The mass jumps to 1.33x: the same thrust now gives 0.38 of the weight, and the vehicle starts to fall.
    flown = feed(guard, 1.33 * vehicle.mass, 0.5 * hover, 0.05, 1.0, -0.2)
    assert any(flown) and flown.index(True) <= 0.02 * RATE and guard.engagements == 1
    assert all(feed(guard, 1.33 * vehicle.mass, 0.5 * hover, 0.1, 1.05, 0.05))  # not yet clearly climbing
    # Climbing relative to the reference: let go after RELEASE_S (the estimate reads high at the clamp).
    held = feed(guard, 1.33 * vehicle.mass, 0.5 * hover, 0.1, 1.15, RELEASE_SPEED + 0.01)
    assert held[0] and not held[-1] and held.index(False) == round(RELEASE_S * RATE) - 1


def test_a_fast_climb_command_or_a_lost_thrust_without_a_fall_does_not_engage() -> None:
    guard, vehicle = make_guard()
    hover = vehicle.mass * vehicle.gravity
    feed(guard, vehicle.mass, hover, 1.0, 0.0, 0.0)
    # A step up in the command that the motors follow over 100 ms: the specific force lags it, nothing is lost.
    lagging = [hover + 0.4 * hover * (1.0 - math.exp(-k / RATE / 0.1)) for k in range(40)]
    for k, measured in enumerate(lagging):
        t = 1.0 + k / RATE
        imu = ImuSample(math.floor(t * 100.0) / 100.0, np.array([0.0, 0.0, measured / vehicle.mass]))
        assert not guard.engaged(State(np.array([0.0, 0.0, HEIGHT]), np.array([0.0, 0.0, -0.1]), LEVEL, imu), 0.0, True)
        guard.sent(1.4 * hover)
    # Thrust lost while the vehicle is still rising towards its reference: no fall to stop yet.
    assert not any(feed(guard, vehicle.mass, 1.4 * hover, 0.05, 1.1, 0.3, measured_thrust=0.4 * hover))


def test_a_vehicle_high_enough_above_its_reference_to_stop_is_left_to_its_controller() -> None:
    vehicle = cfknode.load_config().vehicle
    guard = FallGuard(FallGuardSettings(2.0, 5.0, RATE), vehicle)
    hover = vehicle.mass * vehicle.gravity
    feed(guard, vehicle.mass, hover, 1.0, 0.0, 0.0, above=0.3)
    # A 1.3x mass while sinking at 0.2 m/s: the clamp through 150 ms of lag stops it 0.09 m lower, so 0.3 m
    # above its reference the guard leaves it to its controller ...
    assert not any(feed(guard, 1.3 * vehicle.mass, hover, 0.05, 1.0, -0.2, above=0.3))
    # ... and flies the clamp once it is closer than that.
    assert any(feed(guard, 1.3 * vehicle.mass, hover, 0.05, 1.05, -0.2, above=0.08))


def test_without_an_accelerometer_it_never_engages() -> None:
    guard, vehicle = make_guard()
    for k in range(800):
        assert not guard.engaged(State(np.array([0.0, 0.0, HEIGHT]), np.array([0.0, 0.0, -1.0]), LEVEL), 0.0, True)
        guard.sent(0.3 * vehicle.mass * vehicle.gravity)


class Hover:
    def sample(self, t: np.ndarray) -> cfknode.RefSamples:
        n = t.shape[0]
        return cfknode.RefSamples(t, np.tile([0.0, 0.0, HEIGHT], (n, 1)), np.zeros((n, 3)), np.zeros((n, 3)),
                                  np.zeros(n))


def fly_mass_step(overrides: dict[str, Any], seconds: float = 3.5, step: float = 2.0) -> tuple[float, int, int]:
    """A public-API Controller hovering a 1-D vehicle whose mass steps from 0.5x to 1.33x at ``step`` s, with the thrust
    at the clamp 1.05 of the new weight and 100 ms of motor lag. Returns (the height lost after the step, guarded
    ticks, saturated ticks)."""
    cfg = cfknode.load_config(overrides={"controller.adaptation": "none", **overrides})
    vehicle = cfg.vehicle
    ctrl = cfknode.Controller(cfg.controller, vehicle, ground_z=0.0)
    scale = 1.05 * 1.33 * vehicle.mass * vehicle.gravity / vehicle.max_thrust  # the plant's thrust per command
    period = 1.0 / RATE
    p, v, acting, guarded, saturated = HEIGHT, 0.0, 0.5 * vehicle.mass * vehicle.gravity, 0, 0
    at_step, lowest = math.nan, math.inf
    imu: ImuSample | None = None
    for k in range(int(round(seconds / period))):
        t = k * period
        mass = vehicle.mass * (0.5 if t < step else 1.33)
        if t >= step and math.isnan(at_step):
            at_step = p
        if k % 4 == 0:  # the accelerometer logs at 100 Hz
            imu = ImuSample(t, np.array([0.0, 0.0, acting / mass]))
        command = ctrl.step(t, State(np.array([0.0, 0.0, p]), np.array([0.0, 0.0, v]), LEVEL, imu), Hover())
        guarded += int(command.guarded)
        saturated += int(command.saturated)
        sent = scale * read_setpoint(command.setpoint, vehicle, 0.0, period).thrust_n
        acting = lag_step(acting, sent, period, 0.1)
        a = acting / mass - vehicle.gravity
        p, v = p + period * v + 0.5 * period * period * a, v + period * a
        lowest = min(lowest, p) if t >= step else lowest
    return at_step - lowest, guarded, saturated


def test_the_nominal_mpc_stops_a_fall_at_the_thrust_limit_only_with_the_guard() -> None:
    # The flight of tests/test_thrust_limit.py in one dimension: without the guard the MPC, believing the
    # config's thrust-to-weight, ramps to the clamp too late and sinks 1.3 m; with it the sag is the lag's
    # with the clamp commanded at the step (thrust_sag.step_sag: 0.38 m) and a sample of detection (0.42 m).
    with_guard, guarded, saturated = fly_mass_step({})
    without, never, _ = fly_mass_step({"controller.fall_guard_level": 0.0})
    assert never == 0 and without > 1.0
    assert guarded > 0 and saturated >= guarded  # every guarded tick is flagged: never trained on
    assert step_sag(1.05, 0.5, 1.33, 0.1) < with_guard < step_sag(1.05, 0.5, 1.33, 0.1, reaction_s=0.02)
