"""Plants the controller was not tuned on: sim.motor_time_constant, thrust_map_scale,
battery_sag_per_s, attitude_gain, yaw_gain. At their defaults nothing changes; off them,
each has its physical effect."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cfknode.app.config import ConfigError, MassChange, load_config
from cfknode.app.mission import run_flight
from cfknode.models.quadrotor import quat_to_euler_zyx
from cfknode.sim_backend.crazyflie import SimCrazyflie
from cfknode.sim_backend.plant import (
    heaviest_factor, plant_motor_time_constant, thrust_scale_at, thrust_scale_for_thrust_to_weight, thrust_to_weight,
)
from cfknode.sim_backend.vehicle import CMD_MAX, Vehicle

TX = 0.01
DEFAULTS_SPELLED_OUT = {
    "sim.motor_time_constant": 0.015, "sim.thrust_map_scale": 1.0, "sim.battery_sag_per_s": 0.0,
    "sim.attitude_gain": 1.0, "sim.yaw_gain": 1.0,
}


def _sim(**overrides) -> SimCrazyflie:
    cfg = load_config(overrides={"sim.initial_position": [0.0, 0.0, 20.0], **overrides})
    sim = SimCrazyflie(cfg.vehicle, cfg.sim)
    f = sim.mass * cfg.vehicle.gravity / 4.0
    sim.vehicle.reset(sim.state, [f] * 4)
    sim.firmware.on_rpyt(sim.t, 0.0, 0.0, 0.0, 0)  # unlock
    return sim


def _hover_cmd(sim: SimCrazyflie) -> int:
    return round(sim.mass * sim.vehicle_config.gravity / sim.vehicle_config.newton_per_cmd)


def _stream(sim: SimCrazyflie, duration: float, roll=0.0, pitch=0.0, yawrate=0.0, thrust=None) -> np.ndarray:
    thrust = _hover_cmd(sim) if thrust is None else thrust
    rows = []
    end = sim.t + duration - 1e-9
    while sim.t < end:
        sim.firmware.on_rpyt(sim.t, roll, -pitch, yawrate, thrust)
        sim.step_to(sim.t + TX)
        rows.append((sim.t, *np.degrees(quat_to_euler_zyx(sim.state[6:10])), *sim.state[:6]))
    return np.array(rows)


# ----------------------------------------------------------------------------- defaults change nothing


def test_default_plant_keys_are_the_vehicle_config():
    cfg = load_config()
    assert cfg.sim.motor_time_constant is None
    assert plant_motor_time_constant(cfg.vehicle, cfg.sim) == cfg.vehicle.motor_time_constant
    assert thrust_scale_at(100.0, cfg.sim) == 1.0


def test_plant_keys_at_their_defaults_reproduce_the_sim_bit_for_bit():
    runs = []
    for overrides in ({}, DEFAULTS_SPELLED_OUT):
        sim = _sim(**overrides)
        rows = _stream(sim, 0.6, roll=4.0, pitch=-3.0, yawrate=25.0, thrust=_hover_cmd(sim) + 800)
        runs.append(np.concatenate([rows.ravel(), sim.motor_forces, [sim.battery_voltage]]))
    np.testing.assert_array_equal(runs[0], runs[1])


def test_a_seeded_short_flight_reproduces_bit_for_bit_with_the_defaults_spelled_out(tmp_path):
    short = {"trajectory.duration": 1.0, "trajectory.takeoff_duration": 1.0, "trajectory.settle_duration": 0.2,
             "trajectory.land_duration": 1.0, "trajectory.ramp_duration": 0.5, "log.dir": str(tmp_path)}
    a = run_flight(load_config(overrides=short), name_hint="plain")
    b = run_flight(load_config(overrides={**short, **DEFAULTS_SPELLED_OUT}), name_hint="spelled")
    np.testing.assert_array_equal(a.record.p, b.record.p)
    assert a.outcome.message.startswith("flight complete")


# ----------------------------------------------------------------------------- each key's effect


@pytest.mark.parametrize("tau", [0.04, 0.15])
def test_motor_time_constant_sets_the_plant_lag(tau):
    cfg = load_config(overrides={"sim.initial_position": [0.0, 0.0, 20.0], "sim.motor_time_constant": tau})
    assert cfg.vehicle.motor_time_constant == 0.015  # the controller's belief is untouched
    vehicle = Vehicle(cfg.vehicle, cfg.sim)
    cmd = 0.8 * CMD_MAX
    target = 0.8 * cfg.vehicle.thrust_max_per_motor
    steps = round(tau / cfg.sim.dt)
    for _ in range(steps):
        vehicle.step([cmd] * 4, cfg.vehicle.mass)
    # First-order lag: 1 - 1/e of the step after one time constant.
    assert vehicle.motor_forces[0] / target == pytest.approx(1.0 - math.exp(-1.0), abs=0.01)


@pytest.mark.parametrize("scale", [0.85, 1.15])
def test_thrust_map_scale_scales_the_force_per_command(scale):
    cfg = load_config(overrides={"sim.initial_position": [0.0, 0.0, 20.0], "sim.thrust_map_scale": scale,
                                 "sim.motor_time_constant": 0.0})
    vehicle = Vehicle(cfg.vehicle, cfg.sim)
    cmd = 0.5 * CMD_MAX
    vehicle.step([cmd] * 4, cfg.vehicle.mass)
    np.testing.assert_allclose(vehicle.motor_forces, scale * 0.5 * cfg.vehicle.thrust_max_per_motor, rtol=1e-12)
    az = 4 * scale * 0.5 * cfg.vehicle.thrust_max_per_motor / cfg.vehicle.mass - cfg.vehicle.gravity
    assert vehicle.state[5] == pytest.approx(az * cfg.sim.dt, rel=1e-9)


def test_battery_sag_lowers_the_thrust_over_time():
    sim = _sim(**{"sim.battery_sag_per_s": 0.02, "sim.thrust_map_scale": 0.9})
    assert thrust_scale_at(10.0, sim.sim_config) == pytest.approx(0.9 * 0.8)
    _stream(sim, 2.0, thrust=round(_hover_cmd(sim) / 0.9))
    assert sim.vehicle.thrust_scale == pytest.approx(0.9 * (1.0 - 0.02 * (sim.t - sim.dt)), rel=1e-9)
    # The same hover command no longer holds the vehicle up: it sinks.
    assert sim.state[5] < -0.1


@pytest.mark.parametrize("gain", [0.8, 1.2])
def test_attitude_gain_scales_the_angle_the_firmware_reaches(gain):
    base = _stream(_sim(), 1.5, roll=10.0, pitch=-6.0)
    rows = _stream(_sim(**{"sim.attitude_gain": gain}), 1.5, roll=10.0, pitch=-6.0)
    assert base[-1, 1] == pytest.approx(10.0, abs=0.5)
    # The attitude loop is linear in its setpoint at these angles: the response scales with the gain.
    assert rows[-1, 1] / base[-1, 1] == pytest.approx(gain, rel=0.01)
    assert rows[-1, 2] / base[-1, 2] == pytest.approx(gain, rel=0.01)


def test_yaw_gain_scales_the_yaw_rate():
    sim = _sim(**{"sim.yaw_gain": 1.8})
    rows = _stream(sim, 2.0, yawrate=30.0)
    yaw = np.unwrap(np.radians(rows[:, 3]))
    rate = np.degrees((yaw[-1] - yaw[-51]) / (rows[-1, 0] - rows[-51, 0]))
    assert rate == pytest.approx(-30.0 * 1.8, abs=2.0)  # + on the wire turns clockwise


def test_thrust_to_weight_helper():
    vehicle = load_config().vehicle
    assert thrust_to_weight(vehicle) == pytest.approx(1.545, abs=0.002)
    scale = thrust_scale_for_thrust_to_weight(1.05, vehicle, 1.33)
    assert scale == pytest.approx(0.905, abs=0.002)
    assert thrust_to_weight(vehicle, scale, 1.33) == pytest.approx(1.05, rel=1e-12)
    assert heaviest_factor((MassChange(1.0, 0.5), MassChange(2.0, 1.33))) == 1.33
    assert heaviest_factor(()) == 1.0
    with pytest.raises(ValueError):
        thrust_scale_for_thrust_to_weight(0.0, vehicle)


# ----------------------------------------------------------------------------- config


def test_plant_keys_are_checked():
    assert load_config(overrides={"sim.motor_time_constant": 0.08}).sim.motor_time_constant == 0.08
    for key, bad in (("sim.motor_time_constant", 0.5), ("sim.thrust_map_scale", 2.0), ("sim.attitude_gain", 0.2),
                     ("sim.yaw_gain", 5.0), ("sim.battery_sag_per_s", -0.1), ("sim.motor_time_constant", "fast")):
        with pytest.raises(ConfigError, match=key.split(".")[1]):
            load_config(overrides={key: bad})
