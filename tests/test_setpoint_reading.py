"""The firmware's reading of an RPYT setpoint (cfknode.read_setpoint) against the simulated firmware and the Mellinger layer."""

from __future__ import annotations

import math

import numpy as np
import pytest

import cfknode
from cfknode.app.config import load_config
from cfknode.flight.mellinger import acc_to_setpoint
from cfknode.kernel.setpoint import AttitudeSetpoint, read_setpoint
from cfknode.sim_backend.firmware import Firmware


def test_thrust_is_mapped_clamped_and_cut_below_the_commander_minimum() -> None:
    vehicle = load_config().vehicle
    assert read_setpoint(AttitudeSetpoint(0, 0, 0, 999), vehicle, 0.0, 0.01).thrust_n == 0.0
    assert read_setpoint(AttitudeSetpoint(0, 0, 0, 30000), vehicle, 0.0, 0.01).thrust_n == pytest.approx(
        30000 * vehicle.newton_per_cmd)
    assert read_setpoint(AttitudeSetpoint(0, 0, 0, 65535), vehicle, 0.0, 0.01).thrust_n == pytest.approx(
        vehicle.max_thrust)


def test_the_yaw_rate_is_clockwise_positive_and_integrates_into_the_desired_yaw() -> None:
    vehicle = load_config().vehicle
    target = read_setpoint(AttitudeSetpoint(0, 0, -90.0, 30000), vehicle, 0.0, 0.5)  # -90 deg/s clockwise = CCW
    assert target.yaw_rate == pytest.approx(math.radians(90.0))
    assert target.yaw == pytest.approx(math.radians(45.0))
    near_pi = read_setpoint(AttitudeSetpoint(0, 0, -90.0, 30000), vehicle, math.radians(170.0), 0.5)
    assert near_pi.yaw == pytest.approx(math.radians(-145.0))  # wrapped like the firmware's capAngle


def test_the_simulated_firmware_reads_a_packet_as_the_kernel_does() -> None:
    cfg = load_config()
    fw = Firmware(cfg.vehicle, cfg.sim.dt)
    fw.on_rpyt(0.0, 0.0, 0.0, 0.0, 0)  # the unlock
    fw.on_rpyt(0.01, 5.0, -3.0, 20.0, 65535)  # cflib has already negated pitch on the wire
    sp = fw.last_setpoint
    target = read_setpoint(AttitudeSetpoint(5.0, 3.0, 20.0, 65535), cfg.vehicle, 0.0, cfg.sim.dt)
    assert sp.thrust * cfg.vehicle.newton_per_cmd == pytest.approx(target.thrust_n)
    assert math.radians(sp.yaw_rate) == pytest.approx(target.yaw_rate)


def test_a_mellinger_setpoint_read_back_gives_the_commanded_acceleration() -> None:
    cfg = load_config()
    acc = np.array([1.0, -0.5, 0.3])
    # Once the vehicle holds the attitude it was asked for, the setpoint flies the commanded acceleration.
    level = cfknode.read_setpoint(acc_to_setpoint(acc, 0.0, np.array([1.0, 0.0, 0.0, 0.0]), cfg.vehicle,
                                                  cfg.controller), cfg.vehicle, 0.0, 0.0)
    q = np.array(level.quaternion)
    target = cfknode.read_setpoint(acc_to_setpoint(acc, 0.0, q, cfg.vehicle, cfg.controller), cfg.vehicle, 0.0, 0.0)
    w, x, y, z = target.quaternion
    body_z = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
    flown = target.thrust_n / cfg.vehicle.mass * body_z - [0.0, 0.0, cfg.vehicle.gravity]
    np.testing.assert_allclose(flown, acc, atol=0.02)  # thrust is rounded to whole commands
