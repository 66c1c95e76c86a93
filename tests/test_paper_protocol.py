"""The paper's protocol: reference polygon, plant integration, actuators, mass events, metric."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from cfknode.app.bench.paper.protocol import (
    Actuators,
    ChordCircle,
    MassEvent,
    PaperPlant,
    PaperProtocol,
    improvement_percent,
    per_axis_mse,
    plant_rhs,
    position_mse,
)
from cfknode.app.bench.paper.vehicle import PAPER_ROTORS, PAPER_VEHICLE, plus_mixer


def test_chord_circle_starts_at_r_and_moves_at_constant_speed_on_the_polygon():
    proto = PaperProtocol(radius=3.0, speed=1.2)
    circle = ChordCircle(proto)
    p0, v0 = circle.sample(0.0)
    np.testing.assert_allclose(p0, [3.0, 0.0, 0.0], atol=1e-12)
    t = np.linspace(0.0, proto.duration, 4001)
    p, v = circle.sample(t)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.2, rtol=1e-12)
    assert np.all(p[:, 2] == 0.0)
    # On the chords: inside the circle, never closer than the chord's midpoint.
    dth = (proto.duration + proto.extra_angle) / (proto.waypoints - 1)
    rad = np.linalg.norm(p[:, :2], axis=1)
    assert rad.max() <= 3.0 + 1e-12 and rad.min() >= 3.0 * np.cos(dth / 2) - 1e-12
    # Counter-clockwise, and the position is the integral of the velocity.
    assert np.all(np.diff(np.unwrap(np.arctan2(p[:, 1], p[:, 0]))) > 0)
    np.testing.assert_allclose(np.diff(p, axis=0), 0.5 * (v[1:] + v[:-1]) * np.diff(t)[:, None], atol=1e-4)
    # The path length covered is speed * time (8 s at 1.2 m/s: 9.6 m; samples cut the vertices).
    assert np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)) == pytest.approx(9.6, rel=1e-5)


def test_plant_step_is_scipys_rk45_step_and_close_to_rk4():
    proto = PaperProtocol()
    rng = np.random.default_rng(0)
    plant = PaperPlant(proto)
    x = proto.initial_state()
    x[3:6] = rng.normal(size=3)
    x[6:10] = np.array([0.98, 0.1, -0.15, 0.05])  # not unit: the normalisation term acts
    x[10:13] = rng.normal(size=3)
    u = np.array([0.35, 2e-4, -1e-4, 3e-5])
    plant.state = x.copy()
    ours = plant.step(u).copy()
    ref = solve_ivp(
        lambda _t, s: plant_rhs(s, tuple(u), 0.03, proto.vehicle.inertia, 9.81), (0.0, proto.plant_dt), x,
        first_step=proto.plant_dt,
    ).y[:, -1]
    np.testing.assert_allclose(ours, ref, rtol=1e-13, atol=1e-15)
    rk4 = PaperPlant(PaperProtocol(integrator="rk4"))
    rk4.state = x.copy()
    np.testing.assert_allclose(rk4.step(u), ours, atol=1e-9)
    # The normalisation term pulls |q| toward 1.
    assert abs(np.linalg.norm(ours[6:10]) - 1.0) < abs(np.linalg.norm(x[6:10]) - 1.0)


def test_hover_input_holds_the_plant_still():
    proto = PaperProtocol()
    plant = PaperPlant(proto)
    u = np.array([0.03 * 9.81, 0.0, 0.0, 0.0])
    for _ in range(100):
        plant.step(u)
    np.testing.assert_allclose(plant.state, proto.initial_state(), atol=1e-12)
    assert plant.fallbacks == 0


def test_mass_events_apply_after_their_step():
    proto = PaperProtocol(events=(MassEvent(2.0, -0.015), MassEvent(5.0, 0.025)))
    plant = PaperPlant(proto)
    masses = []
    u = np.array([0.03 * 9.81, 0.0, 0.0, 0.0])
    for _ in range(2600):
        masses.append(plant.mass)  # the mass used by the step about to run
        plant.step(u)
    masses = np.array(masses)
    assert np.all(masses[:1001] == 0.03)  # steps 0..1000 (t = 2.000 -> 2.002 included)
    assert np.all(masses[1001:2501] == pytest.approx(0.015))
    assert np.all(masses[2501:] == pytest.approx(0.040))
    assert proto.event_steps() == {1000: -0.015, 2500: 0.025}


def test_actuators_clip_rotor_speeds_and_the_negative_force_fallback():
    veh = PAPER_VEHICLE
    assert veh.max_thrust == pytest.approx(0.575)
    mixer = plus_mixer(veh)
    exact = Actuators(veh, PAPER_ROTORS, reproduce_fallback=False)
    u = np.array([0.3, 1e-4, -2e-4, 1e-5])
    np.testing.assert_allclose(exact.apply(u), u, rtol=1e-12, atol=1e-15)  # feasible: unchanged
    big = exact.apply(np.array([1.0, 0.0, 0.0, 0.0]))
    assert big[0] == pytest.approx(veh.max_thrust)  # every rotor at 2500 rad/s
    neg = exact.apply(np.array([0.05, 0.01, 0.0, 0.0]))  # rotor 4 would need a negative force
    forces = np.linalg.solve(mixer, neg)
    assert forces.min() == pytest.approx(0.0, abs=1e-15)
    bug = Actuators(veh, PAPER_ROTORS, reproduce_fallback=True)
    neg_bug = bug.apply(np.array([0.05, 0.01, 0.0, 0.0]))
    forces_bug = np.linalg.solve(mixer, neg_bug)
    # k_t * (trim force 0.0737 N)^2: about 1e-10 N instead of 0.
    assert 0.0 < forces_bug.min() < 1e-9
    np.testing.assert_allclose(neg_bug, neg, atol=1e-9)


def test_metric_is_the_mean_over_samples_and_axes():
    pos = np.zeros((4, 3))
    ref = np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 0], [0, 0, 3.0]])
    assert position_mse(pos, ref) == pytest.approx((1 + 4 + 9) / 12)
    np.testing.assert_allclose(per_axis_mse(pos, ref), [0.25, 1.0, 2.25])
    assert improvement_percent(0.2, 0.15) == pytest.approx(25.0)


def test_protocol_rejects_bad_settings():
    with pytest.raises(ValueError):
        PaperProtocol(control_hz=30)
    with pytest.raises(ValueError):
        PaperProtocol(integrator="euler")
    assert PaperProtocol().steps == 4000 and PaperProtocol().hold == 25
