"""SimCrazyflie closed loop: sign conventions through the RPYT wire values, hover, take-off,
watchdog in flight, mass changes, determinism, observers and threads."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.models.quadrotor import quat_to_euler_zyx
from cfknode.sim_backend.crazyflie import SimCrazyflie

TX_PERIOD = 0.01  # 100 Hz streaming, as the radio does


def _parts(cfg):
    return cfg.vehicle, cfg.sim


def make_sim(z: float = 0.0, airborne_hover: bool = False, **overrides) -> SimCrazyflie:
    overrides.setdefault("sim.initial_position", [0.0, 0.0, z])
    # Signs and timings are checked on the rigid body; the realistic plant's terms have their own tests.
    overrides.setdefault("sim.aero", "ideal")
    sim = SimCrazyflie(*_parts(load_config(overrides=overrides)))
    if airborne_hover:
        f = sim.mass * sim.vehicle_config.gravity / 4.0
        sim.vehicle.reset(sim.state, [f] * 4)
    return sim


def hover_cmd(sim: SimCrazyflie) -> int:
    return round(sim.mass * sim.vehicle_config.gravity / sim.vehicle_config.newton_per_cmd)


def send_setpoint(sim: SimCrazyflie, roll: float, pitch: float, yawrate: float, thrust: int) -> None:
    """What cflib's ``Commander.send_setpoint`` puts on the wire: pitch negated, the rest as given."""
    sim.firmware.on_rpyt(sim.t, roll, -pitch, yawrate, thrust)


def stream(sim: SimCrazyflie, duration: float, roll=0.0, pitch=0.0, yawrate=0.0, thrust=None):
    """Stream one user setpoint at 100 Hz for ``duration``; returns (t, roll, pitch, yaw) in degrees."""
    thrust = hover_cmd(sim) if thrust is None else thrust
    rows = []
    end = sim.t + duration - 1e-9
    while sim.t < end:
        send_setpoint(sim, roll, pitch, yawrate, thrust)
        sim.step_to(sim.t + TX_PERIOD)
        rows.append((sim.t, *np.degrees(quat_to_euler_zyx(sim.state[6:10]))))
    return np.array(rows)


def unlock(sim: SimCrazyflie) -> None:
    send_setpoint(sim, 0.0, 0.0, 0.0, 0)


def tilt_compensated(sim: SimCrazyflie, deg: float) -> int:
    return round(hover_cmd(sim) / math.cos(math.radians(deg)))


# ----------------------------------------------------------------------------- hover, take-off


def test_closed_loop_hover_holds_position_and_attitude():
    sim = make_sim(z=1.0, airborne_hover=True)
    unlock(sim)
    att = stream(sim, 3.0)
    np.testing.assert_allclose(sim.state[:3], [0.0, 0.0, 1.0], atol=2e-3)  # only the command's rounding
    np.testing.assert_allclose(sim.state[3:6], 0.0, atol=2e-3)
    assert np.abs(att[:, 1:]).max() < 1e-6
    assert sim.firmware.supervisor_state == "flying"


def test_take_off_from_the_ground():
    sim = make_sim()
    assert sim.vehicle.on_ground
    unlock(sim)
    stream(sim, 0.5, thrust=hover_cmd(sim) - 3000)  # too weak: stays on the ground
    assert sim.state[2] == 0.0 and sim.vehicle.on_ground
    stream(sim, 1.0, thrust=48000)
    a_expected = (48000 * sim.vehicle_config.newton_per_cmd / sim.mass - 9.81)
    assert sim.state[2] == pytest.approx(0.5 * a_expected * 1.0**2, rel=0.1)  # motor lag costs a little
    assert np.abs(sim.state[:2]).max() < 1e-9


# ----------------------------------------------------------------------------- sign conventions


def test_positive_user_pitch_is_nose_down_and_accelerates_forward():
    sim = make_sim(z=20.0, airborne_hover=True)
    unlock(sim)
    att = stream(sim, 1.5, pitch=10.0, thrust=tilt_compensated(sim, 10.0))
    pitch_rh = att[-1, 2]
    assert pitch_rh == pytest.approx(10.0, abs=1.0)
    assert abs(att[-1, 1]) < 0.1
    assert sim.state[3] > 1.0 and abs(sim.state[4]) < 0.05  # +x


def test_positive_roll_is_right_side_down_and_accelerates_right():
    sim = make_sim(z=20.0, airborne_hover=True)
    unlock(sim)
    att = stream(sim, 1.5, roll=10.0, thrust=tilt_compensated(sim, 10.0))
    assert att[-1, 1] == pytest.approx(10.0, abs=1.0)
    assert abs(att[-1, 2]) < 0.1
    assert sim.state[4] < -1.0 and abs(sim.state[3]) < 0.05  # -y


def test_positive_user_yawrate_turns_clockwise_seen_from_above():
    sim = make_sim(z=20.0, airborne_hover=True)
    unlock(sim)
    att = stream(sim, 2.0, yawrate=30.0)
    yaw = np.unwrap(np.radians(att[:, 3]))
    rate = np.degrees((yaw[-1] - yaw[-51]) / (att[-1, 0] - att[-51, 0]))
    assert rate == pytest.approx(-30.0, abs=1.5)
    assert sim.state[12] < 0.0


def test_attitude_step_response_is_stable_and_well_damped():
    sim = make_sim(z=20.0, airborne_hover=True)
    unlock(sim)
    att = stream(sim, 1.5, roll=15.0, thrust=tilt_compensated(sim, 15.0))
    roll = att[:, 1]
    rise = att[np.argmax(roll > 0.9 * 15.0), 0] - att[0, 0] + TX_PERIOD
    assert rise < 0.4
    assert roll.max() < 15.0 * 1.1  # the angle integrator gives a small, slow overshoot
    assert np.all(np.diff(roll) > -0.05)  # no ringing
    rates = sim.state[10:13]
    assert np.abs(rates).max() < 0.05


# ----------------------------------------------------------------------------- watchdog in flight


def test_lost_link_in_flight_levels_out_then_locks_and_falls():
    sim = make_sim(z=20.0, airborne_hover=True)
    unlock(sim)
    stream(sim, 1.0, roll=10.0, thrust=tilt_compensated(sim, 10.0))
    t_last = sim.t - TX_PERIOD
    sim.step_to(t_last + 0.5)
    roll_before = math.degrees(quat_to_euler_zyx(sim.state[6:10])[0])
    assert sim.firmware.supervisor_state == "flying" and roll_before > 9.0
    sim.step_to(t_last + 1.0)
    assert sim.firmware.supervisor_state == "warning_level_out"
    roll, pitch, _ = np.degrees(quat_to_euler_zyx(sim.state[6:10]))
    assert abs(roll) < 1.0 and abs(pitch) < 1.0
    assert sim.firmware.motor_commands[0] > 30000  # the last thrust is kept
    sim.step_to(t_last + 2.2)
    assert sim.firmware.supervisor_state == "locked"
    assert sim.motor_forces.max() < 1e-3 and sim.state[5] < -0.5  # motors off, falling


# ----------------------------------------------------------------------------- scenario, battery


def test_mass_change_takes_effect_at_its_time():
    sim = make_sim(z=20.0, airborne_hover=True, **{"sim.mass_changes": [{"t": 0.5, "factor": 2.0}]})
    nominal = sim.mass
    unlock(sim)
    cmd = hover_cmd(sim)
    stream(sim, 0.5, thrust=cmd)
    assert sim.mass == nominal and abs(sim.state[5]) < 1e-3
    stream(sim, 0.5, thrust=cmd)
    assert sim.mass == pytest.approx(2.0 * nominal)
    # Twice the mass on the same thrust: a = -g/2 from t = 0.5 s.
    assert sim.state[5] == pytest.approx(-0.5 * 9.81 * 0.5, rel=0.02)


def test_battery_voltage_sags_in_flight():
    sim = make_sim(z=5.0, airborne_hover=True, **{"sim.battery_voltage": 4.0})
    assert sim.battery_voltage == pytest.approx(4.0, abs=0.02)
    unlock(sim)
    stream(sim, 1.0)
    v_hover = sim.battery_voltage
    assert 3.55 < v_hover < 3.85
    stream(sim, 1.0)
    assert sim.battery_voltage < v_hover


# ----------------------------------------------------------------------------- stepping, determinism


def _flight(seed: int) -> tuple[np.ndarray, float]:
    sim = make_sim(**{"sim.seed": seed, "sim.wind": [0.5, 0.0, 0.0], "sim.drag": [0.01, 0.01, 0.01]})
    unlock(sim)
    stream(sim, 0.6, roll=3.0, pitch=-2.0, yawrate=20.0, thrust=45000)
    return np.concatenate([sim.state, sim.motor_forces, [sim.battery_voltage]]), float(sim.rng.random())


def test_runs_are_deterministic_for_a_seed():
    a, ra = _flight(3)
    b, rb = _flight(3)
    np.testing.assert_array_equal(a, b)
    assert ra == rb
    _, rc = _flight(4)
    assert rc != ra


def test_step_to_and_observers():
    sim = make_sim()
    seen: list[tuple[float, np.ndarray]] = []
    sim.add_step_observer(lambda t, x: seen.append((t, x)))
    sim.step_to(0.005)
    assert sim.steps == 3 and sim.t == pytest.approx(0.006)
    assert [t for t, _ in seen] == pytest.approx([0.002, 0.004, 0.006])
    assert seen[-1][1].shape == (13,)
    np.testing.assert_array_equal(seen[-1][1], sim.state)
    sim.step_to(0.006)  # already there
    sim.step_to(0.001)  # in the past
    assert sim.steps == 3
    sim.step_to(0.008 + 1e-13)  # within the tolerance of a step boundary
    assert sim.steps == 4


def test_firmware_inputs_from_another_thread_while_stepping():
    sim = make_sim()
    unlock(sim)
    packets = 200

    def radio() -> None:
        for _ in range(packets):
            send_setpoint(sim, 0.0, 0.0, 0.0, 45000)
            time.sleep(0.0002)

    thread = threading.Thread(target=radio)
    thread.start()
    while thread.is_alive():
        sim.step_to(sim.t + 0.002)
        time.sleep(0)
    thread.join()
    assert sim.firmware.setpoints_received == packets + 1
    assert sim.firmware.last_setpoint.thrust == 45000
    assert sim.steps > 0 and sim.t == pytest.approx(sim.steps * sim.dt)
