"""The safety supervisor's state machine and watchdogs, driven tick by tick with fakes (no simulator)."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from cfknode.app.config import ConfigError, load_config
from cfknode.flight.estimator import StateEstimate
from cfknode.app.logs.writer import check_message
from cfknode.kernel.setpoint import AttitudeSetpoint
from cfknode.flight.trajectory import make_trajectory
from cfknode.mocap.source import Pose
from cfknode.models.quadrotor import euler_zyx_to_quat
from cfknode.safety.supervisor import (
    BLIND, CUTOFF_HOLD_S, FLY, OFF, STOP_HOLD_S, State, SupervisorInputs,
)
from cfknode.safety.watchdogs import LinkStatus
from cfknode.app.mission import build_supervisor

RATE = 400.0
PERIOD = 1.0 / RATE
LEVEL = np.array([1.0, 0.0, 0.0, 0.0])
HOVER_SP = AttitudeSetpoint(1.0, -2.0, 0.0, 40000)
SHORT = {
    "trajectory.kind": "hover",
    "trajectory.height": 1.0,
    "trajectory.duration": 1.0,
    "trajectory.takeoff_duration": 1.0,
    "trajectory.settle_duration": 0.5,
    "trajectory.land_duration": 1.0,
}


class FakeRadio:
    def __init__(self) -> None:
        self.setpoints: list[AttitudeSetpoint] = []
        self.extposes = 0
        self.pumps = 0

    def set_setpoint(self, sp: AttitudeSetpoint) -> None:
        self.setpoints.append(sp)

    def set_extpose(self, position: np.ndarray, quaternion: np.ndarray) -> None:
        self.extposes += 1

    def pump(self, now: float) -> None:
        self.pumps += 1


class FakeLog:
    def __init__(self) -> None:
        self.messages: list[tuple[str, float, dict]] = []

    def write(self, topic: str, t: float, msg: dict) -> None:
        self.messages.append((topic, t, dict(msg)))

    def topic(self, name: str) -> list[dict]:
        return [{"t": t, **m} for topic, t, m in self.messages if topic == name]


class Rig:
    """A supervisor with fakes around it, and a tick helper that plays the loop's part."""

    def __init__(self, overrides: dict | None = None, deadlines: bool = False, **inputs) -> None:
        self.cfg = load_config(overrides={**SHORT, **(overrides or {})})
        self.traj = make_trajectory(self.cfg.trajectory, np.zeros(3))
        self.radio = FakeRadio()
        self.log = FakeLog()
        self.sup = build_supervisor(self.cfg, self.radio, trajectory=self.traj, log=self.log,
                                          deadlines_apply=deadlines, inputs=SupervisorInputs(**inputs))
        self.offsets = self.cfg.controller.dt * np.arange(self.cfg.controller.horizon + 1)
        self.k = 0
        self.seen = False
        self.last: tuple[str, object, str] | None = None

    @property
    def now(self) -> float:
        return self.k * PERIOD

    def tick(self, p=None, pose: bool = True, q=LEVEL, fallback: bool = False, missed: bool = False,
             sp: AttitudeSetpoint = HOVER_SP):
        """One tick with the drone at ``p`` (default: on the reference), a fresh pose if ``pose``."""
        now = self.now
        ref = self.traj.sample(now + self.offsets)
        p = ref.p[0].copy() if p is None else np.asarray(p, dtype=float)
        if pose:
            self.seen |= self.sup.accept_pose(now, Pose(now, p, q))
        est = StateEstimate(now, p, np.zeros(3), np.asarray(q, dtype=float), 0.0) if self.seen else None
        action, ref_out, source = self.sup.plan(now, est, ref)
        sent = self.sup.send(now, sp if action is FLY else self.sup.blind_setpoint if action is BLIND else sp)
        self.sup.after_tick(now, fallback, "solver_failed" if fallback else "ok", missed)
        self.k += 1
        self.last = (action, ref_out, source)
        return action, ref_out, source, sent

    def run_until(self, t: float, **kw):
        out = None
        while self.now < t - 1e-9:
            out = self.tick(**kw)
        return out

    def to_track(self):
        self.run_until(self.traj.segments["takeoff"][1] + 0.1)
        assert self.sup.state is State.TRACK


def test_nominal_flight_walks_the_states_and_logs_each_transition():
    rig = Rig()
    action, _, source, sent = rig.tick(pose=False)
    assert rig.sup.state is State.PREFLIGHT and action is OFF and source == "no_state" and sent.thrust == 0
    action, _, _, sent = rig.tick()
    assert rig.sup.state is State.TAKEOFF and action is FLY and sent == HOVER_SP
    rig.run_until(rig.traj.segments["land"][0] + 0.01)
    assert rig.sup.state is State.LAND
    rig.run_until(rig.traj.duration + 0.01)
    assert rig.sup.state is State.LANDED and rig.last[0] is OFF and rig.last[2] == "cutoff"
    assert rig.radio.setpoints[-1].thrust == 0
    assert not rig.sup.finished
    rig.run_until(rig.traj.duration + CUTOFF_HOLD_S + 0.01)
    assert rig.sup.finished
    states = [m["state"] for m in rig.log.topic("/events") if "state" in m]
    assert states == ["PREFLIGHT", "TAKEOFF", "TRACK", "LAND", "LANDED"]
    assert all(m["source"] == "supervisor" for m in rig.log.topic("/events"))
    outcome = rig.sup.outcome()
    assert outcome.state is State.LANDED and outcome.message == "flight complete: landed"
    assert len(rig.log.topic("/safety")) >= 10 * rig.traj.duration
    for topic in ("/safety", "/events"):
        for msg in rig.log.topic(topic):
            as_read = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in msg.items()}
            assert check_message(topic, as_read) == []


def test_the_gate_sends_zeros_unless_flying_and_never_a_nan():
    rig = Rig()
    _, _, _, sent = rig.tick(pose=False, sp=AttitudeSetpoint(0, 0, 0, 50000))
    assert sent.thrust == 0 and rig.radio.setpoints[-1].thrust == 0
    rig.tick()
    _, _, _, sent = rig.tick(sp=AttitudeSetpoint(math.nan, 0.0, 0.0, 40000))
    assert sent.thrust == 0 and rig.sup.state is State.EMERGENCY
    assert "non-finite setpoint" in rig.sup.outcome().message
    assert rig.radio.pumps == rig.k  # every tick pumps the radio through the gate


def test_non_finite_pose_is_ignored_and_not_forwarded():
    rig = Rig()
    rig.tick()
    n = rig.radio.extposes
    assert not rig.sup.accept_pose(rig.now, Pose(rig.now, np.array([np.nan, 0.0, 0.0]), LEVEL))
    assert rig.radio.extposes == n and rig.sup.rejected_poses == 1


def test_crossing_the_hard_fence_lands_inside_the_soft_box():
    rig = Rig()
    rig.to_track()
    action, ref, _, _ = rig.tick(p=[1.55, 0.0, 1.0])
    assert rig.sup.state is State.LAND and action is FLY
    assert ref.p[0, 0] == pytest.approx(1.3)  # landing held at the soft box (1.5 - 0.2 m margin)
    assert ref.p[-1, 2] < 1.0 and np.all(np.diff(ref.p[:, 2]) <= 1e-12)
    assert rig.sup.outcome().cause == "fence"
    # The fence brake: the steeper tilt until the drone is back inside the soft box, then the usual one.
    assert rig.sup.brake_tilt_deg == rig.cfg.safety.fence_brake_tilt_deg == 45.0
    rig.tick(p=[1.35, 0.0, 1.0])
    assert rig.sup.brake_tilt_deg == 45.0
    rig.tick(p=[1.25, 0.0, 1.0])
    assert rig.sup.brake_tilt_deg is None and rig.sup.state is State.LAND


def test_no_fence_brake_outside_a_landing_for_the_fence():
    rig = Rig()
    rig.to_track()
    rig.tick(p=[1.4, 0.0, 1.0])  # in the margin, not across the fence: tracked as usual
    assert rig.sup.state is State.TRACK and rig.sup.brake_tilt_deg is None


def test_far_outside_the_fence_stops_the_motors():
    rig = Rig()
    rig.to_track()
    rig.tick(p=[2.1, 0.0, 1.0])
    assert rig.sup.state is State.EMERGENCY and rig.radio.setpoints[-1].thrust == 0
    rig.run_until(rig.now + STOP_HOLD_S + 0.01)
    assert rig.sup.finished
    assert rig.sup.outcome().message.startswith("motors stopped: 0.60 m outside the geofence on x")


def test_mocap_loss_levels_and_sinks_then_stops():
    rig = Rig()
    rig.to_track()
    for _ in range(int(0.1 * RATE)):
        action, _, _, sent = rig.tick(pose=False)
        assert action is FLY
    action, _, source, sent = rig.tick(pose=False)
    assert action is BLIND and source == "blind" and rig.sup.state is State.LAND
    cfg = rig.cfg
    hover_cmd = cfg.vehicle.mass * cfg.vehicle.gravity / cfg.vehicle.newton_per_cmd
    assert sent.roll_deg == sent.pitch_deg == sent.yawrate_deg == 0.0
    assert 0.85 * hover_cmd < sent.thrust < hover_cmd
    assert rig.sup.blind_acc[2] < 0.0
    rig.run_until(rig.now + 0.39, pose=False)
    assert rig.sup.state is State.LAND
    rig.run_until(rig.now + 0.02, pose=False)
    assert rig.sup.state is State.EMERGENCY and rig.radio.setpoints[-1].thrust == 0
    assert rig.sup.outcome().message.startswith("motors stopped: mocap lost (no frame for 0.50 s)")


def test_mocap_back_before_the_stop_lands_from_where_the_drone_is():
    rig = Rig()
    rig.to_track()
    rig.run_until(rig.now + 0.2, pose=False)
    assert rig.last[0] is BLIND
    action, ref, _, _ = rig.tick(p=[0.1, 0.0, 0.9])
    assert action is FLY and rig.sup.state is State.LAND
    assert ref.p[0] == pytest.approx([0.1, 0.0, 0.9])


def test_tumble_stops_but_one_bad_frame_does_not():
    rig = Rig()
    rig.to_track()
    tilted = np.array(euler_zyx_to_quat(math.radians(70.0), 0.0, 0.0))
    rig.tick(q=tilted)
    rig.tick()
    assert rig.sup.state is State.TRACK
    for _ in range(int(0.05 * RATE) + 1):
        rig.tick(q=tilted)
    assert rig.sup.state is State.EMERGENCY and "tilted 70 deg" in rig.sup.outcome().message


def test_tracking_error_lands_after_it_persists():
    rig = Rig()
    rig.to_track()
    off = rig.traj.sample(np.array([rig.now])).p[0] + [0.0, 0.0, -(rig.cfg.safety.max_tracking_error + 0.05)]
    for _ in range(int(0.1 * RATE)):
        rig.tick(p=off)
    assert rig.sup.state is State.TRACK
    rig.tick(p=off)
    rig.tick(p=off)
    assert rig.sup.state is State.LAND and rig.sup.outcome().cause == "tracking"


def test_low_battery_refuses_take_off():
    rig = Rig(battery_voltage=lambda: 3.55)
    action, _, source, sent = rig.tick()
    assert rig.sup.state is State.IDLE and action is OFF and source == "refused" and sent.thrust == 0
    assert rig.sup.finished
    assert rig.sup.outcome().message == "take-off refused: battery 3.55 V is below 3.7 V"


def test_battery_below_the_in_flight_threshold_lands():
    volts = [3.9]
    rig = Rig(battery_voltage=lambda: volts[0])
    rig.to_track()
    volts[0] = 3.0
    rig.run_until(rig.now + 0.5)
    assert rig.sup.state is State.LAND and rig.sup.outcome().cause == "battery_low"


@pytest.mark.parametrize(
    ("status", "state", "cause"),
    [
        (LinkStatus(lost="Too many packets lost"), State.EMERGENCY, "link_lost"),
        (LinkStatus(silence_s=0.3), State.LAND, "link_silent"),
        (LinkStatus(latency_s=0.25), State.LAND, "link_latency"),
        (LinkStatus(silence_s=0.05, latency_s=0.02), State.TRACK, None),
    ],
)
def test_radio_link_watchdog(status, state, cause):
    link = [LinkStatus()]
    rig = Rig(link_status=lambda now: link[0])
    rig.to_track()
    link[0] = status
    rig.run_until(rig.now + 0.05)
    assert rig.sup.state is state
    if cause:
        assert rig.sup.outcome().cause == cause


def test_a_run_of_missed_deadlines_lands_on_the_wall_clock_only():
    for deadlines, expected in ((True, State.LAND), (False, State.TRACK)):
        rig = Rig(deadlines=deadlines)
        rig.to_track()
        for i in range(39):
            rig.tick(missed=True)
        rig.tick(missed=False)  # a good tick resets the run
        for i in range(40):
            rig.tick(missed=True)
        rig.tick()
        assert rig.sup.state is expected


def test_sustained_mpc_failure_lands_and_short_failures_are_counted_only():
    rig = Rig()
    rig.to_track()
    for _ in range(100):
        rig.tick(fallback=True)
    rig.tick()
    assert rig.sup.state is State.TRACK and rig.sup.fallback_ticks == 100
    for _ in range(200):
        rig.tick(fallback=True)
    rig.tick()
    assert rig.sup.state is State.LAND and rig.sup.outcome().cause == "mpc_failure"
    assert "the geometric fallback flew 300 ticks" in rig.sup.outcome().message


def test_operator_requests_from_another_thread():
    rig = Rig()
    rig.to_track()
    key_reader = threading.Thread(target=rig.sup.request_land)
    key_reader.start()
    key_reader.join()
    rig.tick()
    assert rig.sup.state is State.LAND
    rig.sup.request_stop()
    rig.tick()
    assert rig.sup.state is State.EMERGENCY and rig.sup.outcome().cause == "operator_stop"


def test_interrupt_lands_then_stops():
    rig = Rig()
    rig.to_track()
    rig.sup.interrupt()
    rig.tick()
    assert rig.sup.state is State.LAND and rig.sup.outcome().cause == "sigint"
    rig.sup.interrupt()
    rig.tick()
    assert rig.sup.state is State.EMERGENCY
    assert rig.sup.outcome().message.startswith("motors stopped: second Ctrl-C (SIGINT)")


def test_stop_signals_name_their_cause():
    """Any mix of stop signals: the first lands with its name, the second stops with both."""
    rig = Rig()
    rig.to_track()
    rig.sup.interrupt("SIGHUP")
    rig.tick()
    assert rig.sup.state is State.LAND and rig.sup.outcome().cause == "sighup"
    rig.sup.interrupt("SIGINT")
    rig.tick()
    outcome = rig.sup.outcome()
    assert outcome.state is State.EMERGENCY and outcome.cause == "sigint_stop"
    assert outcome.message.startswith("motors stopped: Ctrl-C (SIGINT) after SIGHUP (terminal closed) at")


def test_an_interrupt_before_take_off_refuses_it():
    rig = Rig()
    rig.sup.interrupt()
    rig.tick()
    assert rig.sup.state is State.IDLE and rig.sup.outcome().message == "take-off refused: Ctrl-C (SIGINT)"


def test_operator_requests_carry_their_cause():
    rig = Rig()
    rig.to_track()
    rig.sup.request_land("cfknode estop --robot cf7 --land", "estop_land")
    rig.tick()
    assert rig.sup.state is State.LAND and rig.sup.outcome().cause == "estop_land"
    rig.sup.request_stop("cfknode estop --robot cf7", "estop_stop")
    rig.tick()
    assert rig.sup.state is State.EMERGENCY
    assert rig.sup.outcome().message.startswith("motors stopped: cfknode estop --robot cf7 at")


def test_disabled_supervisor_ignores_watchdogs_but_not_the_operator():
    rig = Rig({"safety.enabled": False})
    rig.to_track()
    rig.run_until(rig.now + 1.0, pose=False)
    assert rig.sup.state in (State.TRACK, State.LAND) and rig.last[0] is FLY
    rig.tick(p=[5.0, 0.0, 1.0])
    assert rig.sup.state is not State.EMERGENCY
    rig.sup.request_stop()
    rig.tick()
    assert rig.sup.state is State.EMERGENCY


def test_start_pose_far_from_the_trajectory_refuses_take_off():
    rig = Rig()
    rig.tick(p=[0.5, 0.0, 0.0])
    assert rig.sup.state is State.IDLE and rig.sup.outcome().cause == "start_pose"


def test_no_pose_refuses_after_the_preflight_timeout():
    rig = Rig()
    rig.run_until(0.6, pose=False)
    assert rig.sup.state is State.IDLE and rig.sup.finished
    assert "no mocap frame within 0.5 s" in rig.sup.outcome().message


def test_supervisor_landing_cuts_the_motors_at_touchdown():
    rig = Rig()
    rig.to_track()
    rig.sup.request_land()
    _, ref, _, _ = rig.tick()
    start_z = ref.p[0, 2]
    # Follow the landing reference exactly; it ends on the ground and the motors are cut.
    while rig.sup.state is State.LAND:
        _, ref, _, _ = rig.tick(p=rig.last[1].p[0])
    assert rig.sup.state is State.LANDED and rig.radio.setpoints[-1].thrust == 0
    assert start_z == pytest.approx(1.0, abs=1e-6)
    assert rig.sup.outcome().message.startswith("landed: operator e-stop key at")


def test_bad_watchdog_times_are_refused():
    cfg = load_config(overrides={**SHORT, "safety.mocap_stop_s": 0.05})
    with pytest.raises(ConfigError, match="mocap_stop_s"):
        build_supervisor(cfg, FakeRadio(), trajectory=make_trajectory(cfg.trajectory, np.zeros(3)),
                               log=FakeLog(), deadlines_apply=False)
