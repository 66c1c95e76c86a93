"""Mellinger layer: signs, hover thrust (docs/hardware.md#rpyt-setpoint, #thrust-map), tilt and
thrust clamps, yaw rate."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.flight.mellinger import acc_to_setpoint
from cfknode.kernel.setpoint import AttitudeSetpoint, thrust_command
from cfknode.models.quadrotor import euler_zyx_to_quat, quat_to_rotation

CFG = load_config()
VEH, CTL = CFG.vehicle, CFG.controller
G = VEH.gravity
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])


def sp(acc, yaw_des=0.0, q=LEVEL, controller=CTL) -> AttitudeSetpoint:
    return acc_to_setpoint(np.asarray(acc, dtype=float), yaw_des, q, VEH, controller)


def test_hover_is_level_at_the_hover_command():
    s = sp([0.0, 0.0, 0.0])
    assert s.roll_deg == 0.0 and s.pitch_deg == 0.0 and s.yawrate_deg == 0.0
    assert isinstance(s.thrust, int)
    assert s.thrust == round(VEH.mass * G / VEH.newton_per_cmd)
    assert 38_700 <= s.thrust <= 38_900  # ~38,800 at 29 g (docs/hardware.md#thrust-map)


def test_plus_x_gives_positive_pitch():
    s = sp([2.0, 0.0, 0.0])
    assert s.pitch_deg == pytest.approx(math.degrees(math.atan2(2.0, G)))
    assert s.roll_deg == pytest.approx(0.0, abs=1e-12)


def test_plus_y_gives_negative_roll():
    s = sp([0.0, 2.0, 0.0])
    assert s.roll_deg == pytest.approx(-math.degrees(math.atan2(2.0, G)))
    assert s.pitch_deg == pytest.approx(0.0, abs=1e-12)


def test_angles_are_relative_to_the_measured_heading():
    # Facing +y (yaw 90 deg), a +y world acceleration is "forward": pitch, not roll.
    q = euler_zyx_to_quat(0.0, 0.0, math.pi / 2)
    s = sp([0.0, 2.0, 0.0], yaw_des=math.pi / 2, q=q)
    assert s.pitch_deg == pytest.approx(math.degrees(math.atan2(2.0, G)))
    assert s.roll_deg == pytest.approx(0.0, abs=1e-9)


def test_firmware_rebuilds_the_desired_thrust_direction():
    # The firmware composes Rz(its yaw) Ry(pitch) Rx(roll); its z axis must be F_des / |F_des|,
    # whatever the desired yaw, within the tilt limit.
    rng = np.random.default_rng(5)
    for _ in range(300):
        acc = rng.uniform([-4, -4, -4], [4, 4, 4])
        yaw_meas = rng.uniform(-math.pi, math.pi)
        yaw_des = yaw_meas + rng.uniform(-0.5, 0.5)
        q = euler_zyx_to_quat(rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), yaw_meas)
        s = sp(acc, yaw_des, q)
        f = VEH.mass * (acc + np.array([0, 0, G]))
        tilt = math.degrees(math.atan2(math.hypot(f[0], f[1]), f[2]))
        if tilt > CTL.max_tilt_deg - 1e-6:
            continue
        z_fw = quat_to_rotation(euler_zyx_to_quat(math.radians(s.roll_deg), math.radians(s.pitch_deg), yaw_meas))[:, 2]
        np.testing.assert_allclose(z_fw, f / np.linalg.norm(f), atol=1e-12)


def test_tilt_is_limited_keeping_the_vertical_component():
    s = sp([30.0, 0.0, 0.0])
    assert s.pitch_deg == pytest.approx(CTL.max_tilt_deg)
    s = sp([-30.0, -30.0, 0.0])
    z = quat_to_rotation(euler_zyx_to_quat(math.radians(s.roll_deg), math.radians(s.pitch_deg), 0.0))[:, 2]
    assert math.degrees(math.acos(z[2])) == pytest.approx(CTL.max_tilt_deg)
    np.testing.assert_allclose(z[0], z[1])  # direction kept
    # At that attitude the thrust holds the vertical component m g.
    q = euler_zyx_to_quat(math.radians(s.roll_deg), math.radians(s.pitch_deg), 0.0)
    s_at = sp([-30.0, -30.0, 0.0], q=q)
    expected = VEH.mass * G / math.cos(math.radians(CTL.max_tilt_deg))
    assert s_at.thrust == thrust_command(expected, VEH)
    # A different limit from the config.
    ctl = dataclasses.replace(CTL, max_tilt_deg=10.0)
    assert sp([30.0, 0.0, 0.0], controller=ctl).pitch_deg == pytest.approx(10.0)


def test_thrust_clamps_and_free_fall():
    assert sp([0.0, 0.0, 20.0]).thrust == VEH.thrust_cmd_clamp
    fall = sp([3.0, 1.0, -12.0])
    assert fall.thrust == 0 and fall.roll_deg == 0.0 and fall.pitch_deg == 0.0
    # Climbing at 0.3 g needs 1.3 x hover.
    assert sp([0.0, 0.0, 0.3 * G]).thrust == thrust_command(1.3 * VEH.mass * G, VEH)


def test_thrust_uses_the_measured_body_axis():
    tilt = math.radians(20.0)
    q = euler_zyx_to_quat(tilt, 0.0, 0.0)
    s = sp([0.0, 0.0, 0.0], q=q)
    assert s.thrust == thrust_command(VEH.mass * G * math.cos(tilt), VEH)


def test_yaw_rate_sign_gain_clamp_and_wrap():
    # Desired yaw CCW of the measured one -> CCW rate -> negative RPYT yaw rate (CW-positive).
    s = sp([0, 0, 0], yaw_des=0.2)
    assert s.yawrate_deg == pytest.approx(-math.degrees(CTL.yaw_rate_gain * 0.2))
    assert sp([0, 0, 0], yaw_des=-0.2).yawrate_deg == pytest.approx(math.degrees(CTL.yaw_rate_gain * 0.2))
    assert sp([0, 0, 0], yaw_des=2.0).yawrate_deg == pytest.approx(-CTL.max_yaw_rate_deg)
    # Measured 179 deg, desired -179 deg: 2 deg the short way, CCW.
    q = euler_zyx_to_quat(0.0, 0.0, math.radians(179.0))
    s = sp([0, 0, 0], yaw_des=math.radians(-179.0), q=q)
    assert s.yawrate_deg == pytest.approx(-CTL.yaw_rate_gain * 2.0)


def test_thrust_command_helper():
    assert thrust_command(0.0, VEH) == 0
    assert thrust_command(-1.0, VEH) == 0
    assert thrust_command(10.0, VEH) == VEH.thrust_cmd_clamp
    assert thrust_command(1000 * VEH.newton_per_cmd, VEH) == 1000
    assert thrust_command(1000.6 * VEH.newton_per_cmd, VEH) == 1001
    assert isinstance(thrust_command(0.2, VEH), int)


def test_setpoint_is_frozen():
    s = sp([0, 0, 0])
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.thrust = 5  # type: ignore[misc]
