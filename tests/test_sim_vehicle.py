"""The simulated Crazyflie's plant: rigid body + motors, RK4, thrust map, ground, drag, battery, scenario."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from cfknode.app.config import MassChange, load_config
from cfknode.models.quadrotor import NUMPY, euler_zyx_to_quat, quat_to_euler_zyx, quat_to_rotation, rigid_body_rhs
from cfknode.sim_backend.battery import Battery
from cfknode.sim_backend.scenario import drag_force, mass_at
from cfknode.sim_backend.vehicle import CMD_MAX, THRUST_MIN, Vehicle, command_to_force, motor_wrench


def make_vehicle(**overrides):
    cfg = load_config(overrides=overrides)
    return cfg, Vehicle(cfg.vehicle, cfg.sim)


def airborne_state(z=10.0, q=(1.0, 0.0, 0.0, 0.0), w=(0.0, 0.0, 0.0), v=(0.0, 0.0, 0.0)):
    return np.array([0.0, 0.0, z, *v, *q, *w])


def hover_force(cfg):
    return cfg.vehicle.mass * cfg.vehicle.gravity / 4.0


def force_to_cmd(cfg, force):
    return force / cfg.vehicle.thrust_max_per_motor * CMD_MAX


# ----------------------------------------------------------------------------- thrust map


def test_command_to_force_is_linear_with_motor_cutoff_and_clamps():
    fmax = 0.12
    assert command_to_force(CMD_MAX, fmax) == pytest.approx(fmax)
    assert command_to_force(40000, fmax) == pytest.approx(40000 / 65535 * fmax)
    assert command_to_force(90000, fmax) == pytest.approx(fmax)  # clamped to the motor's range
    assert command_to_force(-5, fmax) == 0.0
    cutoff_cmd = THRUST_MIN / fmax * CMD_MAX  # ~6990
    assert command_to_force(cutoff_cmd - 1.0, fmax) == 0.0
    assert command_to_force(cutoff_cmd + 1.0, fmax) == pytest.approx((cutoff_cmd + 1.0) / CMD_MAX * fmax)
    # docs/hardware.md#thrust-map: about 38,800 holds a 29 g vehicle.
    cfg = load_config()
    hover_cmd = force_to_cmd(cfg, hover_force(cfg))
    assert 38500 < hover_cmd < 39100


# ----------------------------------------------------------------------------- geometry


def test_motor_wrench_matches_the_legacy_layout():
    d, k = 0.046 / math.sqrt(2.0), 0.00699
    t, mx, my, mz = motor_wrench(0.1, 0.0, 0.0, 0.0, d, k)  # m1 front-right, CCW rotor
    assert t == pytest.approx(0.1)
    assert mx < 0  # right side lifted: rolls left side down (negative roll)
    assert my < 0  # front lifted: nose up (negative right-handed pitch)
    assert mz < 0  # a CCW rotor's reaction torque turns the body clockwise
    _, mx4, my4, mz4 = motor_wrench(0.0, 0.0, 0.0, 0.1, d, k)  # m4 front-left, CW rotor
    assert mx4 > 0 and my4 < 0 and mz4 > 0
    assert mx4 == pytest.approx(0.1 * d) and mz4 == pytest.approx(0.1 * k)
    # Equal forces: pure thrust.
    assert motor_wrench(0.07, 0.07, 0.07, 0.07, d, k)[1:] == pytest.approx((0.0, 0.0, 0.0), abs=1e-15)


def test_float_rhs_equals_the_numpy_model():
    cfg, veh = make_vehicle(**{"sim.drag": [0.01, 0.02, 0.03], "sim.wind": [0.5, -0.2, 0.1]})
    q = euler_zyx_to_quat(0.2, -0.1, 0.7)
    x = [0.1, 0.2, 0.3, 0.4, -0.5, 0.6, *q, 1.0, -2.0, 3.0, 0.05, 0.06, 0.07, 0.08]
    dx = veh.derivative(x, 0.03, [0.1, 0.0, 0.05, 0.02])
    u = motor_wrench(0.05, 0.06, 0.07, 0.08, cfg.vehicle.arm_length / math.sqrt(2), cfg.vehicle.thrust_to_torque)
    force = np.array(drag_force(0.4, -0.5, 0.6, cfg.sim.drag, cfg.sim.wind))
    ref = rigid_body_rhs(np.array(x[:13]), np.array(u), 0.03, cfg.vehicle.inertia, cfg.vehicle.gravity, NUMPY, force=force)
    np.testing.assert_allclose(dx[:13], ref, rtol=1e-12, atol=1e-12)
    tau = cfg.vehicle.motor_time_constant
    np.testing.assert_allclose(dx[13:], [(0.1 - 0.05) / tau, -0.06 / tau, (0.05 - 0.07) / tau, (0.02 - 0.08) / tau])


# ----------------------------------------------------------------------------- hover, integration


def test_hover_is_an_equilibrium():
    cfg, veh = make_vehicle()
    f = hover_force(cfg)
    veh.reset(airborne_state(z=1.0), [f] * 4)
    cmd = [force_to_cmd(cfg, f)] * 4
    for _ in range(1500):  # 3 s
        veh.step(cmd, cfg.vehicle.mass)
    x = veh.state
    np.testing.assert_allclose(x[:3], [0.0, 0.0, 1.0], atol=1e-9)
    np.testing.assert_allclose(x[3:6], 0.0, atol=1e-9)
    np.testing.assert_allclose(x[6:10], [1.0, 0.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(veh.motor_forces, [f] * 4, rtol=1e-12)


def test_free_fall_is_exact_and_mass_does_not_matter():
    cfg, veh = make_vehicle()
    veh.reset(airborne_state(z=10.0, v=(1.0, -0.5, 2.0)))
    for _ in range(500):  # 1 s, motors off
        veh.step([0, 0, 0, 0], 0.05)
    g = cfg.vehicle.gravity
    np.testing.assert_allclose(veh.state[:3], [1.0, -0.5, 10.0 + 2.0 - 0.5 * g], atol=1e-10)
    np.testing.assert_allclose(veh.state[3:6], [1.0, -0.5, 2.0 - g], atol=1e-10)


def _spin(dt: float, duration: float = 1.0) -> np.ndarray:
    cfg, veh = make_vehicle(**{"sim.dt": dt})
    veh.reset(airborne_state(z=100.0, q=euler_zyx_to_quat(0.3, -0.2, 0.5), w=(4.0, 1.0, -6.0)))
    for _ in range(round(duration / dt)):
        veh.step([0, 0, 0, 0], cfg.vehicle.mass)
    return veh.state


def test_rk4_converges_at_fourth_order_on_torque_free_rotation():
    ref = _spin(0.0001)
    err_coarse = np.linalg.norm(_spin(0.004)[6:] - ref[6:])
    err_fine = np.linalg.norm(_spin(0.002)[6:] - ref[6:])
    assert err_fine < 1e-6
    ratio = err_coarse / err_fine
    assert 11.0 < ratio < 22.0  # 2^4 = 16 for a fourth-order method


def test_rk4_conserves_rotational_energy_and_momentum():
    cfg = load_config()
    J = np.array(cfg.vehicle.inertia)
    w0 = np.array([4.0, 1.0, -6.0])
    x = _spin(0.002, duration=2.0)
    w = x[10:13]
    R = quat_to_rotation(x[6:10])
    R0 = quat_to_rotation(euler_zyx_to_quat(0.3, -0.2, 0.5))
    assert 0.5 * J @ w**2 == pytest.approx(0.5 * J @ w0**2, rel=1e-7)
    # Angular momentum is constant in the world frame.
    np.testing.assert_allclose(R @ (J * w), R0 @ (J * w0), rtol=1e-6, atol=1e-12)
    assert np.linalg.norm(x[6:10]) == pytest.approx(1.0, abs=1e-14)


# ----------------------------------------------------------------------------- motors


def test_motor_lag_is_first_order_with_the_configured_time_constant():
    cfg, veh = make_vehicle(**{"vehicle.motor_time_constant": 0.02})
    veh.reset(airborne_state(z=50.0))
    fmax = cfg.vehicle.thrust_max_per_motor
    for _ in range(10):  # one time constant
        veh.step([CMD_MAX] * 4, cfg.vehicle.mass)
    np.testing.assert_allclose(veh.motor_forces, fmax * (1.0 - math.exp(-1.0)), rtol=1e-6)
    for _ in range(40):  # five time constants in all
        veh.step([CMD_MAX] * 4, cfg.vehicle.mass)
    np.testing.assert_allclose(veh.motor_forces, fmax * (1.0 - math.exp(-5.0)), rtol=1e-6)


def test_motor_below_thrust_min_spins_down():
    cfg, veh = make_vehicle(**{"vehicle.motor_time_constant": 0.02})
    veh.reset(airborne_state(z=50.0), [0.05] * 4)
    low = force_to_cmd(cfg, THRUST_MIN * 0.9)
    for _ in range(10):
        veh.step([low] * 4, cfg.vehicle.mass)
    np.testing.assert_allclose(veh.motor_forces, 0.05 * math.exp(-1.0), rtol=1e-6)


# ----------------------------------------------------------------------------- ground


def test_resting_on_the_ground_until_thrust_exceeds_weight():
    cfg, veh = make_vehicle(**{"sim.initial_position": [0.5, -0.3, 0.0]})
    assert veh.on_ground
    below = force_to_cmd(cfg, 0.95 * hover_force(cfg))
    for _ in range(500):
        veh.step([below] * 4, cfg.vehicle.mass)
    np.testing.assert_array_equal(veh.state[:6], [0.5, -0.3, 0.0, 0.0, 0.0, 0.0])
    assert veh.on_ground
    assert veh.motor_forces[0] == pytest.approx(0.95 * hover_force(cfg), rel=1e-6)  # motors spun up
    above = force_to_cmd(cfg, 1.2 * hover_force(cfg))
    for _ in range(250):
        veh.step([above] * 4, cfg.vehicle.mass)
    assert not veh.on_ground
    assert veh.state[2] > 0.05 and veh.state[5] > 0.5


def test_touchdown_stops_and_levels_the_vehicle_keeping_yaw():
    cfg, veh = make_vehicle()
    q = euler_zyx_to_quat(math.radians(20), math.radians(-10), math.radians(60))
    veh.reset(airborne_state(z=0.2, q=q, v=(0.3, 0.1, -1.0)))
    for _ in range(200):
        veh.step([0, 0, 0, 0], cfg.vehicle.mass)
    x = veh.state
    assert veh.on_ground
    assert x[2] == 0.0
    np.testing.assert_array_equal(x[3:6], 0.0)
    roll, pitch, yaw = quat_to_euler_zyx(x[6:10])
    assert roll == pytest.approx(0.0, abs=1e-12) and pitch == pytest.approx(0.0, abs=1e-12)
    assert math.degrees(yaw) == pytest.approx(60.0, abs=1e-9)
    # Tumbling down: the rates are zeroed too.
    veh.reset(airborne_state(z=0.2, q=q, w=(1.0, -2.0, 0.5)))
    for _ in range(200):
        veh.step([0, 0, 0, 0], cfg.vehicle.mass)
    assert veh.on_ground
    np.testing.assert_array_equal(veh.state[10:13], 0.0)
    np.testing.assert_allclose(veh.state[7:9], 0.0, atol=1e-15)


def test_initial_position_below_ground_is_rejected():
    cfg = load_config(overrides={"sim.initial_position": [0.0, 0.0, -0.1]})
    with pytest.raises(ValueError, match="initial_position"):
        Vehicle(cfg.vehicle, cfg.sim)


# ----------------------------------------------------------------------------- drag, wind, mass


def test_drag_force_acts_on_air_relative_velocity():
    assert drag_force(1.0, 0.0, -2.0, (0.1, 0.2, 0.3), (0.0, 0.0, 0.0)) == pytest.approx((-0.1, 0.0, 0.6))
    assert drag_force(0.0, 0.0, 0.0, (0.1, 0.2, 0.3), (2.0, -1.0, 0.0)) == pytest.approx((0.2, -0.2, 0.0))
    assert drag_force(2.0, -1.0, 0.0, (0.1, 0.2, 0.3), (2.0, -1.0, 0.0)) == pytest.approx((0.0, 0.0, 0.0))


def test_wind_carries_a_hovering_vehicle_to_the_wind_speed():
    cfg, veh = make_vehicle(**{"sim.drag": [0.01, 0.01, 0.0], "sim.wind": [1.0, -0.5, 0.0]})
    f = hover_force(cfg)
    veh.reset(airborne_state(z=5.0), [f] * 4)
    cmd = [force_to_cmd(cfg, f)] * 4
    steps = 5000  # 10 s = 3.4 time constants m/d
    for _ in range(steps):
        veh.step(cmd, cfg.vehicle.mass)
    frac = 1.0 - math.exp(-0.01 * steps * cfg.sim.dt / cfg.vehicle.mass)
    np.testing.assert_allclose(veh.state[3:5], [1.0 * frac, -0.5 * frac], rtol=1e-6)
    assert veh.state[2] == pytest.approx(5.0, abs=1e-9)


def test_mass_schedule_applies_from_the_first_step_at_or_after_the_change():
    changes = (MassChange(t=2.0, factor=0.5), MassChange(t=5.0, factor=1.33))
    dt = 0.002
    assert mass_at(999 * dt, 0.03, changes) == pytest.approx(0.03)
    assert mass_at(1000 * dt, 0.03, changes) == pytest.approx(0.015)  # 1000 * 0.002 need not equal 2.0 exactly
    assert mass_at(2.0 - 1e-12, 0.03, changes) == pytest.approx(0.015)
    assert mass_at(4.999, 0.03, changes) == pytest.approx(0.015)
    assert mass_at(2500 * dt, 0.03, changes) == pytest.approx(0.03 * 1.33)
    assert mass_at(0.0, 0.03, ()) == 0.03
    # Unordered lists work; factors are relative to the nominal mass, not cumulative.
    assert mass_at(6.0, 0.03, tuple(reversed(changes))) == pytest.approx(0.03 * 1.33)


# ----------------------------------------------------------------------------- battery


def test_battery_sags_under_load_and_discharges():
    bat = Battery(4.1)
    assert bat.voltage == pytest.approx(4.1 - 0.15 * 0.1)
    hover = [0.029 * 9.81 / 4] * 4
    v_hover = bat.update(hover, 0.002)
    assert 0.2 < 4.1 - v_hover < 0.45  # typical idle -> hover sag of a CF2.1
    assert 1.6 < bat.current < 2.6
    v_start = v_hover
    for _ in range(30000):  # 60 s of hover
        bat.update(hover, 0.002)
    assert bat.charge_drawn == pytest.approx(bat.current * 60.0 / 3600.0, rel=0.05)
    drop = v_start - bat.voltage
    expected = 1.2 * bat.charge_drawn / 0.25  # linear open-circuit curve, 3.0..4.2 V over 250 mAh
    assert drop == pytest.approx(expected, rel=0.1)
    # Load off: the sag recovers, the drawn charge does not.
    idle = bat.update([0.0] * 4, 0.002)
    assert idle > bat.open_circuit_voltage - 0.02 and idle < 4.1 - 0.05


def test_motor_lag_can_be_disabled_but_not_under_resolved():
    # The config refuses a motor without lag (config_bounds); the plant itself still supports it.
    cfg = load_config()
    no_lag = dataclasses.replace(cfg.vehicle, motor_time_constant=0.0)
    veh = Vehicle(no_lag, cfg.sim)
    veh.reset(airborne_state(z=50.0))
    veh.step([40000] * 4, cfg.vehicle.mass)
    np.testing.assert_allclose(veh.motor_forces, 40000 / CMD_MAX * cfg.vehicle.thrust_max_per_motor)
    with pytest.raises(ValueError, match="motor_time_constant"):
        Vehicle(dataclasses.replace(cfg.vehicle, motor_time_constant=0.0005), cfg.sim)
