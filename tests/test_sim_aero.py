"""The realistic plant's terms (``sim.aero: realistic``): each one's sign and size at its documented
operating point (docs/hardware.md#simulator), each one off when its key is 0, and the whole plant
with every term at 0 the ideal plant to the bit."""

from __future__ import annotations

import json
import math

import pytest

from cfknode.app.config import ConfigError, load_config
from cfknode.sim_backend.aero import ground_effect_fraction, measured_downwash_force_z
from cfknode.sim_backend.aero_vehicle import AeroVehicle, make_vehicle
from cfknode.sim_backend.crazyflie import SimCrazyflie
from cfknode.sim_backend.vehicle import Vehicle
from cfknode.sim_backend.world import SimWorld
from tests.test_sim_ideal_plant import FIXTURE, ideal_trajectory

ALL_OFF = {"rotor_drag": 0.0, "inflow": 0.0, "ground_effect": 0.0, "downwash": 0.0, "fast_rms": 0.0,
           "fast_rms_per_speed2": 0.0}
G = 9.81


def _terms(**on: float) -> dict[str, float]:
    """Overrides: the realistic plant with only the terms named in ``on`` (others 0)."""
    terms = {**ALL_OFF, **on}
    return {"sim.aero": "realistic", **{f"sim.aero_terms.{k}": v for k, v in terms.items()}}


def _accel(vehicle_overrides: dict, z: float = 1.0, v=(0.0, 0.0, 0.0), q=(1.0, 0.0, 0.0, 0.0),
           wind=(0.0, 0.0, 0.0), thrust: float = 1.0) -> tuple[float, float, float]:
    """World acceleration [m/s^2] of the plant at ``thrust`` x hover thrust, at height ``z``, velocity ``v``."""
    cfg = load_config(overrides={**vehicle_overrides, "sim.wind": list(wind)})
    vehicle = make_vehicle(cfg.vehicle, cfg.sim)
    motor = thrust * cfg.vehicle.mass * cfg.vehicle.gravity / 4.0
    vehicle.reset([0.0, 0.0, z, *v, *q, 0.0, 0.0, 0.0], [motor] * 4)
    d = vehicle.derivative(vehicle.state_list(), cfg.vehicle.mass, [motor] * 4)
    return d[3], d[4], d[5]


def test_the_default_is_the_realistic_plant_and_ideal_selects_the_rigid_body():
    cfg = load_config()
    assert cfg.sim.aero == "realistic" and isinstance(make_vehicle(cfg.vehicle, cfg.sim), AeroVehicle)
    ideal = load_config(overrides={"sim.aero": "ideal"})
    assert type(make_vehicle(ideal.vehicle, ideal.sim)) is Vehicle


def test_every_term_at_zero_is_the_ideal_plant_to_the_bit():
    digest, _ = ideal_trajectory(_terms())
    assert digest == json.loads(FIXTURE.read_text())["sha256"]


# ----------------------------------------------------------------------------- rotor drag


@pytest.mark.parametrize("speed", [1.0, -2.0])
def test_rotor_drag_opposes_the_airspeed_at_0_25_per_m_s(speed):
    ax, ay, az = _accel(_terms(rotor_drag=0.25), v=(speed, 0.0, 0.0))
    assert ax == pytest.approx(-0.25 * speed, rel=1e-9)
    assert ay == pytest.approx(0.0, abs=1e-12)
    assert az == pytest.approx(0.0, abs=1e-9)  # hover thrust holds it; level: no drag along the axis


def test_rotor_drag_acts_on_the_air_not_the_ground():
    # Still in a 1 m/s wind: pushed downwind; moving with the wind: no drag.
    assert _accel(_terms(rotor_drag=0.25), wind=(0.0, 1.0, 0.0))[1] == pytest.approx(0.25, rel=1e-9)
    assert _accel(_terms(rotor_drag=0.25), v=(0.0, 1.0, 0.0), wind=(0.0, 1.0, 0.0))[1] == 0.0


def test_rotor_drag_grows_with_rotor_speed_and_is_off_at_zero():
    # Four times the hover thrust is twice the rotor speed: twice the drag.
    assert _accel(_terms(rotor_drag=0.25), v=(1.0, 0.0, 0.0), thrust=4.0)[0] == pytest.approx(-0.5, rel=1e-9)
    assert _accel(_terms(rotor_drag=0.25), v=(1.0, 0.0, 0.0), thrust=0.0)[0] == 0.0  # rotors stopped
    assert _accel(_terms(), v=(1.0, 0.0, 0.0))[0] == 0.0


# ----------------------------------------------------------------------------- inflow


@pytest.mark.parametrize("vz", [1.0, -0.5])
def test_climbing_loses_thrust_at_0_4_per_m_s(vz):
    az = _accel(_terms(inflow=0.4), v=(0.0, 0.0, vz))[2]
    assert az == pytest.approx(-0.4 * vz, rel=1e-9)
    assert _accel(_terms(inflow=0.4), v=(1.0, 0.0, 0.0))[0] == 0.0  # level: horizontal flight is in the rotor plane


def test_inflow_is_along_the_rotor_axis_when_tilted():
    tilt = math.radians(20.0)
    q = (math.cos(tilt / 2), math.sin(tilt / 2), 0.0, 0.0)  # rolled: the axis leans toward -y
    ax, ay, az = _accel(_terms(inflow=0.4), v=(0.0, 0.0, 1.0), q=q)
    # The loss is 0.4 * (v . b) along b, on top of the tilted hover thrust's own components.
    hover_y, hover_z = -math.sin(tilt) * G, math.cos(tilt) * G - G
    loss = 0.4 * math.cos(tilt)
    assert ay == pytest.approx(hover_y + loss * math.sin(tilt), rel=1e-9)
    assert az == pytest.approx(hover_z - loss * math.cos(tilt), rel=1e-9)
    assert ax == pytest.approx(0.0, abs=1e-12)


# ----------------------------------------------------------------------------- ground effect


def test_ground_effect_is_ten_percent_at_3_to_5_cm_and_gone_above_0_15_m():
    for z in (0.03, 0.04, 0.05):
        assert 0.095 <= ground_effect_fraction(z, 1.0) <= 0.11
    assert ground_effect_fraction(0.10, 1.0) == pytest.approx(2.1 / 29.0)
    assert ground_effect_fraction(0.15, 1.0) == 0.0 and ground_effect_fraction(1.0, 1.0) == 0.0
    heights = [0.01 * k for k in range(16)]
    values = [ground_effect_fraction(z, 1.0) for z in heights]
    assert all(a >= b for a, b in zip(values, values[1:]))  # never stronger further up
    assert ground_effect_fraction(0.04, 0.5) == pytest.approx(0.5 * ground_effect_fraction(0.04, 1.0))


def test_ground_effect_lifts_a_hovering_vehicle_near_the_floor_only():
    az = _accel(_terms(ground_effect=1.0), z=0.04)[2]
    assert az == pytest.approx(G * ground_effect_fraction(0.04, 1.0), rel=1e-9)
    assert _accel(_terms(ground_effect=1.0), z=0.5)[2] == pytest.approx(0.0, abs=1e-12)
    assert _accel(_terms(), z=0.04)[2] == pytest.approx(0.0, abs=1e-12)


def test_ground_effect_lets_a_vehicle_leave_the_floor_a_little_below_its_weight():
    def lifts(overrides: dict) -> bool:
        cfg = load_config(overrides=overrides)
        vehicle = make_vehicle(cfg.vehicle, cfg.sim)
        cmd = 0.95 * cfg.vehicle.mass * G / 4.0 / cfg.vehicle.thrust_max_per_motor * 65535
        for _ in range(100):
            vehicle.step([cmd] * 4, cfg.vehicle.mass)
        return not vehicle.on_ground

    assert lifts(_terms(ground_effect=1.0)) and not lifts({"sim.aero": "ideal"}) and not lifts(_terms())


# ----------------------------------------------------------------------------- downwash


def test_measured_downwash_is_about_0_08_n_at_0_2_to_0_3_m_below_a_hovering_crazyflie():
    thrust = 0.029 * G
    for gap in (0.2, 0.25, 0.3):
        force = measured_downwash_force_z((0.0, 0.0, 1.0), (0.0, 0.0, 1.0 + gap), thrust, 1.0, 0.058)
        assert -0.085 <= force <= -0.075
        assert -force / thrust == pytest.approx(0.28, abs=0.015)
    centre = measured_downwash_force_z((0.0, 0.0, 1.0), (0.0, 0.0, 1.3), thrust, 1.0, 0.058)
    off = measured_downwash_force_z((0.05, 0.0, 1.0), (0.0, 0.0, 1.3), thrust, 1.0, 0.058)
    assert off / centre == pytest.approx(5.7 / 8.3, abs=0.02)  # the jet is ~6 cm wide
    assert measured_downwash_force_z((0.15, 0.0, 1.0), (0.0, 0.0, 1.3), thrust, 1.0, 0.058) > 0.05 * centre
    assert measured_downwash_force_z((0.0, 0.0, 1.3), (0.0, 0.0, 1.0), thrust, 1.0, 0.058) == 0.0  # upper: none
    assert measured_downwash_force_z((0.0, 0.0, 1.0), (0.0, 0.0, 1.3), 0.0, 1.0, 0.058) == 0.0  # motors off
    assert measured_downwash_force_z((0.0, 0.0, 1.0), (0.0, 0.0, 1.3), thrust, 0.0, 0.058) == 0.0  # scaled off


def _stacked_world(gap: float, **overrides) -> SimWorld:
    sims = []
    for i, z in enumerate((1.0, 1.0 + gap)):
        cfg = load_config(overrides={"sim.initial_position": [0.0, 0.0, z], "sim.seed": i, **overrides})
        sims.append(SimCrazyflie(cfg.vehicle, cfg.sim))
    world = SimWorld(sims, cfg.sim.downwash)
    for sim in sims:
        sim.vehicle.reset(sim.state, [sim.mass * G / 4.0] * 4)
    return world


def test_the_realistic_world_puts_the_measured_wake_on_the_lower_drone():
    world = _stacked_world(0.25, **_terms(downwash=1.0))
    world.step_to(world.dt)
    lower, upper = (s.vehicle.external_force for s in world.sims)
    assert lower[2] == pytest.approx(-8.4 / 29.0 * 0.029 * G, rel=1e-6) and upper == (0.0, 0.0, 0.0)
    quiet = _stacked_world(0.25, **_terms())
    quiet.step_to(quiet.dt)
    assert quiet.sims[0].vehicle.external_force == (0.0, 0.0, 0.0)


def test_realistic_plant_refuses_the_ideal_wake_model_too():
    with pytest.raises(ConfigError, match="sim.aero_terms.downwash"):
        load_config(overrides={"sim.aero": "realistic", "sim.downwash.enabled": True})


# ----------------------------------------------------------------------------- configuration


@pytest.mark.parametrize("overrides, says", [
    ({"sim.aero": "turbulent"}, "must be one of ideal, realistic"),
    ({"sim.aero_terms.rotor_drag": -0.1}, "out of range"),
    ({"sim.aero_terms.fast_band_hz": [5.0, 2.0]}, "low edge below its high edge"),
    ({"sim.aero_terms.fast_band_hz": [1.0, 30.0], "sim.dt": 0.01}, "quarter of the plant's step rate"),
])
def test_bad_aero_settings_are_one_line_config_errors(overrides, says):
    with pytest.raises(ConfigError, match=says) as err:
        load_config(overrides=overrides)
    assert "\n" not in str(err.value)


def test_a_gust_on_the_realistic_plant_pushes_through_the_rotors():
    from cfknode.app.config import Gust
    from cfknode.sim_backend.faults import install_faults

    cfg = load_config(overrides={**_terms(rotor_drag=0.25), "sim.initial_position": [0.0, 0.0, 1.0]})
    faults = load_config(overrides={"faults.gusts": [{"t": 0.01, "duration": 0.01, "wind": [4.0, 0.0, 0.0]}]}).faults
    assert faults.gusts == (Gust(0.01, 0.01, (4.0, 0.0, 0.0)),)
    sim = SimCrazyflie(cfg.vehicle, cfg.sim)
    install_faults(sim, faults)
    assert isinstance(sim.vehicle, AeroVehicle)
    hover = [cfg.vehicle.mass * G / 4.0 / cfg.vehicle.thrust_max_per_motor * 65535] * 4
    sim.vehicle.reset([0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0], [cfg.vehicle.mass * G / 4.0] * 4)
    vx = []
    for _ in range(15):
        sim.vehicle.step(hover, cfg.vehicle.mass)
        vx.append(sim.vehicle.state[3])
    assert vx[4] == 0.0  # calm before 10 ms
    # During the 10 ms gust: 0.25 m/s^2 per m/s of the 4 m/s airspeed, about 1 m/s^2.
    assert (vx[9] - vx[4]) / 0.01 == pytest.approx(1.0, rel=0.05)
    assert vx[14] < vx[10]  # the rotors' drag slows it after
