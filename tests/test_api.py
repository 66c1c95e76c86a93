"""The public API as a simulator plug-in uses it: the names, one meaning of ground_z, the geometric
controller without the layer, a plant that hands over the exact state every tick, and the log protocol."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import cfknode
from cfknode.app.config import load_config


def _state(t: float, p, v=(0.0, 0.0, 0.0)) -> cfknode.StateEstimate:
    return cfknode.StateEstimate(t, np.asarray(p, float), np.asarray(v, float), np.array([1.0, 0, 0, 0]), 0.0)


def test_every_public_name_resolves():
    for name in cfknode.__all__:
        assert getattr(cfknode, name) is not None
    assert "AdaptationEstimate" in cfknode.__all__ and "OnlineLearning" in cfknode.__all__


def test_a_guessed_floor_is_said_when_the_vehicle_starts_in_the_air():
    cfg = load_config()
    circle = cfknode.Circle(radius=0.5, speed=0.4, height=1.0)
    guessed = cfknode.Controller(cfg.controller, cfg.vehicle)
    assert guessed.ground_z is None
    with pytest.warns(UserWarning, match=r"first state's height \(z = 1.00 m\)"):
        guessed.step(0.0, _state(0.0, [0.5, 0, 1.0]), circle)
    assert guessed.ground_z == 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        given = cfknode.Controller(cfg.controller, cfg.vehicle, ground_z=0.0)
        given.step(0.0, _state(0.0, [0.5, 0, 1.0]), circle)
        on_floor = cfknode.Controller(cfg.controller, cfg.vehicle)
        on_floor.step(0.0, _state(0.0, [0.0, 0, 0.02]), circle)  # starts on the floor: the guess is right
    assert given.ground_z == 0.0 and on_floor.ground_z == 0.02


def test_online_learning_takes_the_controllers_floor():
    cfg = load_config()
    controller = cfknode.Controller(cfg.controller, cfg.vehicle, ground_z=0.3)
    session = cfknode.online_learning(controller, cfg)
    learner = session.start()
    try:
        assert learner.s.ground_z == 0.3
    finally:
        session.stop()


def test_the_geometric_controller_flies_without_the_layer_unless_asked(tmp_path):
    assert load_config(overrides={"controller.kind": "geometric"}).controller.adaptation == "none"
    assert load_config(overrides={"controller.kind": "geometric", "controller.adaptation": "dob"}).controller.adaptation == "dob"
    user = tmp_path / "c.yaml"
    user.write_text("controller:\n  kind: geometric\n  adaptation: dob\n")
    assert load_config(user).controller.adaptation == "dob"
    assert load_config().controller.adaptation == "dob"  # the MPC keeps its layer


def _fly_exact(seconds: float, mass_factor: float, step_at: float) -> tuple[list, list]:
    """A point mass whose exact state the controller gets every 400 Hz tick (pose_fresh left True)."""
    cfg = load_config()
    vehicle, dt = cfg.vehicle, 1.0 / cfg.controller.rate_hz
    circle = cfknode.Circle(radius=0.5, speed=0.4, height=1.0)
    start = circle.sample(np.zeros(1))
    p, v, q, yaw = start.p[0].copy(), start.v[0].copy(), np.array([1.0, 0, 0, 0]), 0.0
    controller = cfknode.Controller(cfg.controller, vehicle, ground_z=0.0)
    layers, errors = [], []
    for k in range(int(seconds / dt)):
        t = k * dt
        command = controller.step(t, cfknode.StateEstimate(t, p, v, q, yaw), circle)
        layers.append(command.layer)
        target = cfknode.read_setpoint(command.setpoint, vehicle, yaw, dt)
        q, yaw = np.array(target.quaternion), target.yaw
        body_z = np.array([2 * (q[1] * q[3] + q[0] * q[2]), 2 * (q[2] * q[3] - q[0] * q[1]), 1 - 2 * (q[1] ** 2 + q[2] ** 2)])
        mass = vehicle.mass * (mass_factor if t >= step_at else 1.0)
        v = v + dt * (target.thrust_n / mass * body_z - [0.0, 0.0, vehicle.gravity])
        p = p + dt * v
        errors.append(float(np.linalg.norm(p - circle.sample(np.array([t + dt])).p[0])))
    return layers, errors


def test_a_simulator_that_passes_the_exact_state_every_tick_raises_no_false_alarm():
    layers, errors = _fly_exact(5.0, 1.0, np.inf)
    assert all(isinstance(e, cfknode.AdaptationEstimate) for e in layers)
    assert not any(e.stepping for e in layers)  # noise-free input: the step detector stays quiet
    assert abs(layers[-1].thrust_scale - 1.0) < 0.01 and max(errors) < 0.01


def test_with_the_exact_state_a_mass_step_is_taken_and_tracked_a_bounded_time():
    cfg = load_config()
    layers, errors = _fly_exact(6.0, 1.3, 2.0)
    rate = cfg.controller.rate_hz
    longest = run = 0
    for e in layers:
        run = run + 1 if e.stepping else 0
        longest = max(longest, run)
    assert longest / rate <= cfg.controller.adaptation_settings.step_max_s + 1e-9
    assert layers[-1].thrust_scale == pytest.approx(1.3, abs=0.03)
    assert np.sqrt(np.mean(np.square(errors[-int(rate):]))) < 0.01


class ListLog:
    """The ``Log`` protocol as a user writes it."""

    def __init__(self) -> None:
        self.writes: list[tuple[str, float, dict]] = []

    def write(self, topic: str, t: float, msg: dict) -> None:
        assert isinstance(topic, str) and topic.startswith("/") and isinstance(t, float) and "t" not in msg
        self.writes.append((topic, t, msg))


def test_online_learning_writes_the_documented_log_protocol():
    cfg = load_config()
    log = ListLog()
    controller = cfknode.Controller(cfg.controller, cfg.vehicle, ground_z=0.0)
    circle = cfknode.Circle(radius=0.5, speed=0.4, height=1.0)
    p, v = circle.sample(np.zeros(1)).p[0].copy(), circle.sample(np.zeros(1)).v[0].copy()
    with cfknode.online_learning(controller, cfg, log=log) as learner:
        for k in range(int(2.0 * cfg.controller.rate_hz)):
            t = k / cfg.controller.rate_hz
            ref = circle.sample(np.array([t]))
            controller.step(t, _state(t, ref.p[0], ref.v[0]), circle)
    assert learner.stats.rounds_sent > 0
    assert {topic for topic, _, _ in log.writes} & {"/training", "/model"}


def test_the_solver_reports_its_statistics_and_compiles_into_the_configured_cache(tmp_path):
    import dataclasses

    from cfknode.flight.mpc import TranslationalMpc

    # A short horizon: its C compiles in about 1.5 s, the default's in about 6.
    cfg = load_config(overrides={"controller.cache_dir": str(tmp_path / "cache"), "controller.horizon": 5})
    mpc = TranslationalMpc(cfg.controller, cfg.vehicle)
    controller = cfknode.Controller(cfg.controller, cfg.vehicle, solver=mpc, ground_z=0.0)
    circle = cfknode.Circle(radius=0.5, speed=0.4, height=1.0)
    for k in range(5):
        controller.step(k / 400, _state(k / 400, [0.5, 0, 1.0]), circle)
    stats = controller.solver.stats()
    assert isinstance(stats, cfknode.SolverStats) and stats.solves == 5 and stats.failures == 0
    if mpc.compiled is not None:  # a C compiler is on this machine: the code went where it was told
        assert any((tmp_path / "cache").rglob("*.so"))
    assert dataclasses.asdict(stats)["rescues"] == mpc.rescues
