"""The simulated firmware alone: commander decoding, unlock, mixer, supervisor and watchdog sequences.

The firmware is driven at 500 Hz on a fixed level state (no plant): what matters here is
what it does with its inputs and timers.
"""

from __future__ import annotations

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.sim_backend.firmware import (
    SUPERVISOR_PERIOD,
    Firmware,
    cap_angle,
    firmware_attitude,
    legacy_mixer,
)
from cfknode.models.quadrotor import euler_zyx_to_quat

DT = 0.002
LEVEL = [0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]


class Bench:
    """Drives a Firmware on a fixed state at 500 Hz, optionally streaming RPYT at 100 Hz."""

    def __init__(self) -> None:
        cfg = load_config()
        self.fw = Firmware(cfg.vehicle, DT)
        self.k = 0
        self.log: list[tuple[float, str, tuple[int, int, int, int]]] = []

    @property
    def t(self) -> float:
        return self.k * DT

    def run(self, duration: float, rpyt: tuple[float, float, float, int] | None = None) -> None:
        end = self.k + round(duration / DT)
        while self.k < end:
            if rpyt is not None and self.k % 5 == 0:
                self.fw.on_rpyt(self.t, *rpyt)
            motors = self.fw.step(self.t, LEVEL)
            self.log.append((self.t, self.fw.supervisor_state, motors))
            self.k += 1

    def first_time_in(self, state: str) -> float:
        return next(t for t, s, _ in self.log if s == state)


def take_off(bench: Bench, thrust: int = 40000, duration: float = 1.0) -> None:
    bench.fw.on_rpyt(bench.t, 0.0, 0.0, 0.0, 0)  # unlock
    bench.run(duration, (0.0, 0.0, 0.0, thrust))
    assert bench.fw.supervisor_state == "flying"


# ----------------------------------------------------------------------------- commander


def test_thrust_is_locked_until_a_zero_thrust_packet():
    b = Bench()
    b.fw.on_rpyt(0.0, 0.0, 0.0, 0.0, 40000)
    assert b.fw.thrust_locked and b.fw.last_setpoint.thrust == 0
    b.run(0.2, (0.0, 0.0, 0.0, 40000))
    assert all(m == (0, 0, 0, 0) for _, _, m in b.log)
    assert b.fw.supervisor_state == "idle"
    b.fw.on_rpyt(b.t, 0.0, 0.0, 0.0, 0)
    assert not b.fw.thrust_locked
    b.fw.on_rpyt(b.t, 0.0, 0.0, 0.0, 40000)
    assert b.fw.last_setpoint.thrust == 40000
    assert b.fw.step(b.t, LEVEL) == (40000, 40000, 40000, 40000)


def test_rpyt_thrust_floor_and_clamp_and_sign_decoding():
    b = Bench()
    fw = b.fw
    fw.on_rpyt(0.0, 0.0, 0.0, 0.0, 0)
    fw.on_rpyt(0.0, 0.0, 0.0, 0.0, 999)
    assert fw.last_setpoint.thrust == 0
    fw.on_rpyt(0.0, 0.0, 0.0, 0.0, 1000)
    assert fw.last_setpoint.thrust == 1000
    fw.on_rpyt(0.0, 0.0, 0.0, 0.0, 65535)
    assert fw.last_setpoint.thrust == 60000
    # cflib put -user_pitch on the wire: the firmware keeps it (legacy pitch, + = nose up)
    # and negates the yaw rate into its CCW-positive convention.
    fw.on_rpyt(0.1, 5.0, -7.0, 30.0, 20000)
    sp = fw.last_setpoint
    assert (sp.roll, sp.pitch, sp.yaw_rate, sp.thrust, sp.timestamp) == (5.0, -7.0, -30.0, 20000, 0.1)
    assert fw.setpoints_received == 5


def test_extpose_is_stored_and_counted():
    fw = Bench().fw
    fw.on_extpose(0.01, np.array([1.0, 2.0, 3.0]), (0.0, 0.0, 0.0, 1.0))
    fw.on_extpose(0.02, (1.5, 2.0, 3.0), (0.0, 0.0, 0.7071, 0.7071))
    assert fw.extposes_received == 2
    assert fw.last_extpose.t == 0.02
    assert fw.last_extpose.position == (1.5, 2.0, 3.0)
    assert fw.last_extpose.quaternion_xyzw == (0.0, 0.0, 0.7071, 0.7071)


# ----------------------------------------------------------------------------- mixer


def test_mixer_signs_follow_the_legacy_layout():
    m1, m2, m3, m4 = legacy_mixer(30000, 1000, 0, 0)  # + roll: right side down
    assert (m1, m2, m3, m4) == (29500, 29500, 30500, 30500)
    assert legacy_mixer(30000, 0, 1000, 0) == (30500, 29500, 29500, 30500)  # + legacy pitch: nose up
    assert legacy_mixer(30000, 0, 0, 1000) == (31000, 29000, 31000, 29000)
    assert legacy_mixer(30000, 3, -3, 0) == (29998, 30000, 30002, 30000)  # int16 halving truncates toward 0


def test_mixer_caps_by_the_excess_preserving_differences():
    motors = legacy_mixer(60000, 20000, 0, 3000)
    uncapped = np.array([60000 - 10000 + 3000, 60000 - 10000 - 3000, 60000 + 10000 + 3000, 60000 + 10000 - 3000])
    excess = uncapped.max() - 65535
    assert excess > 0
    np.testing.assert_array_equal(motors, uncapped - excess)
    assert max(motors) == 65535
    # Low side: clamped at 0 (no idle thrust on a CF2.1).
    assert legacy_mixer(2000, 20000, 0, 0) == (0, 0, 12000, 12000)


def test_attitude_conventions_of_the_firmware_estimate():
    roll, pitch, yaw = firmware_attitude(*euler_zyx_to_quat(np.radians(10), np.radians(20), np.radians(30)))
    assert (roll, pitch, yaw) == pytest.approx((10.0, -20.0, 30.0))  # pitch reported legacy (inverted)
    assert cap_angle(190.0) == pytest.approx(-170.0) and cap_angle(-540.0) == pytest.approx(-180.0)


def test_rate_loop_outputs_saturate_at_int16():
    b = Bench()
    b.fw.on_rpyt(0.0, 0.0, 0.0, 0.0, 0)
    b.fw.on_rpyt(0.0, 0.0, 0.0, 0.0, 30000)
    spinning = LEVEL[:10] + [20.0, 0.0, 0.0]  # 1150 deg/s roll rate
    b.fw.step(0.0, spinning)
    assert b.fw.control_outputs[0] == -32767
    assert b.fw.motor_commands == (30000 + 16383, 30000 + 16383, 30000 - 16383, 30000 - 16383)


# ----------------------------------------------------------------------------- supervisor


def test_watchdog_levels_out_at_half_a_second_keeping_thrust():
    b = Bench()
    take_off(b)
    b.fw.on_rpyt(b.t, 10.0, -5.0, 20.0, 42000)  # last packet: tilted, yawing, 42000
    t_last = b.t
    b.run(0.6)
    t_warn = b.first_time_in("warning_level_out") - t_last
    assert 0.5 < t_warn <= 0.5 + SUPERVISOR_PERIOD + 1e-9
    # Level out: roll, pitch and yaw rate zeroed, the last thrust kept.
    sp = b.fw.active_setpoint
    assert (sp.roll, sp.pitch, sp.yaw_rate, sp.thrust) == (0.0, 0.0, 0.0, 42000)
    assert b.fw.setpoint.roll == 10.0  # the commander still holds the stale packet


def test_watchdog_recovers_when_setpoints_resume_before_two_seconds():
    b = Bench()
    take_off(b)
    b.run(1.0)
    assert b.fw.supervisor_state == "warning_level_out"
    b.run(0.2, (0.0, 0.0, 0.0, 40000))
    assert b.fw.supervisor_state == "flying"


def test_watchdog_locks_at_two_seconds_and_stays_locked():
    b = Bench()
    take_off(b)
    t_last = b.t - 5 * DT  # the last streamed packet
    b.run(2.5)
    t_lock = b.first_time_in("locked") - t_last
    assert 2.0 < t_lock <= 2.0 + SUPERVISOR_PERIOD + 1e-9
    assert all(m == (0, 0, 0, 0) for t, s, m in b.log if s == "locked")
    # Locked for good: setpoints are ignored, even a fresh unlock.
    received = b.fw.setpoints_received
    b.fw.on_rpyt(b.t, 0.0, 0.0, 0.0, 0)
    b.run(1.0, (0.0, 0.0, 0.0, 40000))
    assert b.fw.supervisor_state == "locked"
    assert b.fw.setpoints_received == received and b.fw.setpoints_blocked > 0
    assert b.fw.motor_commands == (0, 0, 0, 0)


def test_gotcha_stop_streaming_right_after_cutting_thrust_locks():
    b = Bench()
    take_off(b)
    b.run(0.1, (0.0, 0.0, 0.0, 0))  # touchdown: thrust cut, still "flying" (2 s hysteresis)
    assert b.fw.supervisor_state == "flying"
    b.run(3.0)  # then silence
    states = [s for _, s, _ in b.log]
    assert "warning_level_out" in states and "landed" not in states
    assert b.fw.supervisor_state == "locked"


def test_streaming_zeros_past_the_hysteresis_lands_then_silence_is_harmless():
    b = Bench()
    take_off(b)
    t_cut = b.t
    b.run(2.2, (0.0, 0.0, 0.0, 0))
    assert b.fw.supervisor_state == "landed"
    assert 2.0 <= b.first_time_in("landed") - t_cut <= 2.0 + SUPERVISOR_PERIOD + 1e-9
    b.run(5.0)
    assert b.fw.supervisor_state == "landed"
    # It can fly again from landed.
    b.run(0.2, (0.0, 0.0, 0.0, 35000))
    assert b.fw.supervisor_state == "flying"


def test_notify_setpoint_stop_then_high_level_stop_lands_instead_of_locking():
    b = Bench()
    take_off(b)
    b.run(0.1, (0.0, 0.0, 0.0, 0))
    b.fw.on_notify_setpoint_stop(b.t)
    b.fw.on_hl_stop(b.t)
    b.run(5.0)
    states = {s for _, s, _ in b.log}
    assert "warning_level_out" not in states and "locked" not in states
    assert b.fw.supervisor_state == "landed"
    assert b.fw.setpoint.source == "high_level" and b.fw.setpoint.thrust == 0
    assert b.fw.setpoint.timestamp == pytest.approx(b.t - DT)  # the planner keeps feeding


def test_notify_without_a_high_level_planner_still_locks():
    b = Bench()
    take_off(b)
    b.run(0.1, (0.0, 0.0, 0.0, 0))
    b.fw.on_notify_setpoint_stop(b.t)  # the planner was never used: it feeds nothing
    b.run(3.0)
    assert b.fw.supervisor_state == "locked"


def test_streamed_setpoint_takes_priority_back_and_disables_the_planner():
    b = Bench()
    take_off(b)
    b.fw.on_notify_setpoint_stop(b.t)
    b.fw.on_hl_stop(b.t)
    b.run(0.1)
    assert b.fw.motor_commands == (0, 0, 0, 0)  # the planner's null setpoints
    b.run(0.1, (0.0, 0.0, 0.0, 41000))
    assert b.fw.setpoint.source == "rpyt" and b.fw.motor_commands == (41000,) * 4
    b.run(3.0)  # the planner is disabled again, so silence now trips the watchdog
    assert b.fw.supervisor_state == "locked"


def test_stop_setpoint_cuts_motors_at_once_and_refreshes_the_watchdog():
    b = Bench()
    take_off(b)
    b.fw.on_stop(b.t)
    assert b.fw.step(b.t, LEVEL) == (0, 0, 0, 0)
    assert b.fw.last_setpoint.source == "stop"
    b.k += 1
    # Keep sending stop setpoints: the watchdog stays satisfied and it lands after the hysteresis.
    for _ in range(300):
        b.fw.on_stop(b.t)
        b.run(0.01)
    assert b.fw.supervisor_state == "landed"


def test_control_returns_an_array_and_resets_pids_while_thrust_is_zero():
    wound = Bench().fw
    wound.on_rpyt(0.0, 0.0, 0.0, 0.0, 0)
    wound.on_rpyt(0.0, 20.0, 0.0, 0.0, 30000)
    for i in range(50):  # the integrators wind up against a state that never rolls
        out = wound.control(i * DT, np.array(LEVEL))
    assert isinstance(out, np.ndarray) and out.shape == (4,)
    assert out[2] > out[0]  # asked to roll right: left motors push harder
    first_wound = wound.control(50 * DT, np.array(LEVEL))
    wound.on_rpyt(0.1, 20.0, 0.0, 0.0, 0)
    np.testing.assert_array_equal(wound.control(0.1, np.array(LEVEL)), 0.0)
    wound.on_rpyt(0.102, 20.0, 0.0, 0.0, 30000)
    after_reset = wound.control(0.102, np.array(LEVEL))
    fresh = Bench().fw
    fresh.on_rpyt(0.0, 0.0, 0.0, 0.0, 0)
    fresh.on_rpyt(0.0, 20.0, 0.0, 0.0, 30000)
    np.testing.assert_array_equal(after_reset, fresh.control(0.0, np.array(LEVEL)))
    assert first_wound[2] - first_wound[0] > after_reset[2] - after_reset[0]
