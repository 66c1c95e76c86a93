"""``sim.air_model``: the realistic plant's own air terms as the MPC's model, the ceiling of ``bench learning``.

The model must be the plant's air (the same force for the same state), linearised consistently, refused where
it would be meaningless, and, flown, it must take what the layer cannot on a manoeuvre where the air turns
faster than the layer's filters."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cfknode.app.config import ConfigError, load_config
from cfknode.app.mission import air_model_observers, build_model_slot
from cfknode.sim_backend.aero import measured_downwash_force_z, rotor_and_ground_force, rotor_speed_ratio
from cfknode.sim_backend.air_model import AirModel
from cfknode.sim_backend.timed_swap import SwapAt

CFG = load_config()
G = CFG.vehicle.gravity
MASS = CFG.vehicle.mass
TERMS = CFG.sim.aero_terms


def _plant_state(p, v, acc) -> list[float]:
    """The 17-state (p, v, q wxyz, w, motor forces) of a vehicle whose thrust gives the specific force ``acc`` + g."""
    thrust = np.asarray(acc, dtype=float) + [0.0, 0.0, G]
    b = thrust / np.linalg.norm(thrust)
    q = np.array([1.0 + b[2], -b[1], b[0], 0.0])  # the rotation taking the world z onto b
    q /= np.linalg.norm(q)
    motor = MASS * float(np.linalg.norm(thrust)) / 4.0
    return [*p, *v, *q, 0.0, 0.0, 0.0, motor, motor, motor, motor]


@pytest.mark.parametrize("p, v, acc", [
    ((0.0, 0.0, 1.0), (0.6, -0.3, 0.8), (2.0, -1.0, 1.5)),  # climbing through a turn
    ((0.2, 0.1, 0.04), (0.5, 0.0, 0.0), (0.0, 0.5, -0.3)),  # over the floor: the ground effect
    ((0.0, 0.0, 1.0), (-1.2, 0.4, -0.5), (-3.0, 0.0, 0.0)),
])
def test_the_model_is_the_plant_s_air_for_the_same_state(p, v, acc):
    x = _plant_state(p, v, acc)
    speed = rotor_speed_ratio(*x[13:17], MASS * G / 4.0)
    force = rotor_and_ground_force(x, (0.0, 0.0, 0.0), TERMS.rotor_drag * MASS * speed, TERMS.inflow * MASS * speed,
                                   TERMS.ground_effect)
    model = AirModel(TERMS, G)
    got = model.evaluate(np.array([*p, *v]), np.array(acc))
    assert got == pytest.approx(np.array(force) / MASS, abs=1e-9)
    assert np.linalg.norm(got) > 0.05  # a real force, not two zeros agreeing


def test_the_wake_of_the_drone_above_is_the_plant_s():
    lower, upper = np.array([0.0, 0.0, 1.0]), np.array([0.03, -0.02, 1.3])
    expected = measured_downwash_force_z(lower, upper, MASS * G, TERMS.downwash, TERMS.downwash_width) / MASS
    model = AirModel(TERMS, G, neighbour=True)
    assert model.takes_neighbour and not AirModel(TERMS, G).takes_neighbour
    x, u = np.array([*lower, 0.0, 0.0, 0.0]), np.zeros(3)
    assert model.evaluate(x, u, upper)[2] == pytest.approx(expected, rel=1e-9)
    assert expected < -1.0  # a quarter of the weight, about
    assert model.evaluate(x, u, lower + [0.0, 0.0, -0.3])[2] == pytest.approx(0.0, abs=1e-12)  # a drone below: none
    assert model.evaluate(x, u)[2] == pytest.approx(0.0, abs=1e-12)  # no drone above


def test_the_linearisation_is_exact_at_the_nodes_and_close_nearby():
    rng = np.random.default_rng(3)
    x = np.column_stack([rng.uniform(-1, 1, (20, 2)), rng.uniform(0.02, 1.5, 20), rng.uniform(-1.5, 1.5, (20, 3))])
    u = rng.uniform(-3, 3, (20, 3))
    nb = x[:, 0:3] + [0.02, 0.0, 0.3]
    model = AirModel(TERMS, G, neighbour=True)
    c, jx, ju = model.linearise(x, u, nb)
    assert c.shape == (20, 3) and jx.shape == (20, 3, 6) and ju.shape == (20, 3, 3)
    affine = lambda xs, us: c + np.einsum("nij,nj->ni", jx, xs) + np.einsum("nij,nj->ni", ju, us)  # noqa: E731
    assert affine(x, u) == pytest.approx(model.evaluate(x, u, nb), abs=1e-9)
    # Off the nodes the error is second order; the wake is a known force there, with no slope in the position.
    dx, du = 1e-4 * rng.standard_normal((20, 6)), 1e-4 * rng.standard_normal((20, 3))
    dx[:, 2] = 0.0  # the ground table's kinks are the one non-smooth input
    c0, jx0, ju0 = model.linearise(x, u)
    assert jx == pytest.approx(jx0) and ju == pytest.approx(ju0)
    wake = model.evaluate(x, u, nb) - model.evaluate(x, u)
    assert affine(x + dx, u + du) == pytest.approx(model.evaluate(x + dx, u + du) + wake, abs=1e-6)
    assert np.abs(jx[:, 0:2, 3:5]).max() > 0.2  # the drag's slope, about 0.25 per m/s


@pytest.mark.parametrize("overrides, why", [
    ({"online.enabled": True}, "online learning"),
    ({"controller.model": "some.ckpt"}, "controller.model"),
    ({"sim.aero": "ideal"}, "ideal plant"),
    ({"controller.kind": "geometric"}, "geometric"),
    ({"backend": "cf"}, "simulation only"),
    ({"sim.air_model_terms": "wake"}, "needs a fleet"),  # a single drone has no wake: a zero model
    ({"sim.air_model_terms": "wake", "fleet.size": 2}, "neighbour_input"),
])
def test_the_air_model_is_refused_where_it_means_nothing(overrides, why):
    cfg = load_config(overrides={"sim.air_model": True, **overrides})
    with pytest.raises(ConfigError, match=why):
        build_model_slot(cfg)


def test_the_air_model_is_flown_from_the_config():
    slot = build_model_slot(load_config(overrides={"sim.air_model": True}))
    assert slot is not None and isinstance(slot.model, AirModel) and slot.model.beyond_layer is None
    assert build_model_slot(load_config()) is None  # off by default: the plain MPC


def test_the_air_model_can_arrive_when_a_learner_s_first_model_would():
    """``sim.air_model_from_s``: the slot flies nothing until then, and the air model from that tick on, once."""
    cfg = load_config(overrides={"sim.air_model": True, "sim.air_model_from_s": 4.7})
    slot = build_model_slot(cfg)
    assert slot is not None and slot.model is None
    (observer,) = air_model_observers(cfg, slot)
    assert isinstance(observer, SwapAt)
    tick = type("Tick", (), {})
    for t in (0.0, 2.0, 4.69):
        tick.t = t
        observer.on_tick(tick)
    assert slot.model is None and slot.version == 0
    tick.t = 4.7025
    observer.on_tick(tick)
    assert isinstance(slot.model, AirModel) and slot.version == 1 and slot.swaps[-1].t == 4.7025
    tick.t = 5.0
    observer.on_tick(tick)
    assert slot.version == 1 and len(slot.swaps) == 1  # once
    # From take-off (the default) the slot holds the model at once and nothing swaps.
    assert air_model_observers(load_config(overrides={"sim.air_model": True}), slot) == []
    assert isinstance(build_model_slot(load_config(overrides={"sim.air_model": True})).model, AirModel)


def test_the_wake_terms_are_the_wake_alone():
    """``sim.air_model_terms: wake``, a model of the wake's ceiling: the drone above's wake as the plant's, and
    none of the drone's own air (drag, inflow, floor), which stays the layer's."""
    cfg = load_config(overrides={"sim.air_model": True, "sim.air_model_terms": "wake", "fleet.size": 2,
                                 "fleet.neighbour_input": True})
    wake, full = build_model_slot(cfg).model, AirModel(TERMS, G, neighbour=True)
    assert wake.takes_neighbour
    # Fast and climbing, 4 cm over the floor, 0.25 m under the other drone, slightly aside.
    x, u, upper = np.array([0.0, 0.0, 0.04, 0.8, -0.5, 0.6]), np.array([1.0, 0.5, 0.3]), np.array([0.02, 0.0, 0.29])
    assert wake.evaluate(x, u)[:] == pytest.approx(np.zeros(3), abs=1e-12)  # no drone above: nothing
    assert wake.evaluate(x, u, upper) == pytest.approx([0.0, 0.0, full._wake(x[None], upper[None])[0]], abs=1e-12)
    assert wake.evaluate(x, u, upper)[2] < -1.0
    assert np.linalg.norm(full.evaluate(x, u)) > 0.3  # the own air it leaves out is real


def test_the_plant_s_air_beside_the_layer_takes_the_inflow_the_layer_cannot(tmp_path):
    """The vertical oscillation's inflow turns every second: the layer's 0.5-1 Hz offset lags it, the model knows it."""
    from cfknode.app.bench.learning import Job, run_job
    from cfknode.app.bench.learning_cells import CELLS

    cell = next(c for c in CELLS if c.name == "vertical A=0.3 f=0.5")
    runs = {row: run_job(Job(cell, row, 0, str(tmp_path), 4.0)) for row in ("layer", "air+layer")}
    assert all(math.isfinite(r.mse) and not r.fell and not r.tripped for r in runs.values())
    assert runs["air+layer"].mse < 0.5 * runs["layer"].mse


def test_an_air_model_that_arrives_late_changes_the_flight_from_then(tmp_path):
    """``sim.air_model_from_s`` in a flight: the swap happens there and the flight flies the model from then (the
    empty slot before it is the unit test's above)."""
    from cfknode.app.bench.learning import Job, run_job
    from cfknode.app.bench.learning_cells import CELLS

    cell = next(c for c in CELLS if c.name == "vertical A=0.3 f=0.5")
    short = (("trajectory.takeoff_duration", 1.5), ("trajectory.settle_duration", 0.5),
             ("trajectory.land_duration", 1.5))
    late = {t: run_job(Job(cell, "air+layer", 0, str(tmp_path), 2.0, (*short, ("sim.air_model_from_s", t))))
            for t in (3.0, 60.0)}  # the pattern runs from about 2 s to 4 s of flight
    assert all(math.isfinite(r.mse) and not r.tripped for r in late.values())
    assert late[3.0].mse != late[60.0].mse  # 60 s: never arrived
