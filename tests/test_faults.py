"""Fault-injection scenarios (cfknode/scenarios/*.yaml) flown through the whole stack in lockstep.

Each scenario asserts: the end state (the supervisor's, and the simulated vehicle and firmware:
on the ground, motors off), that the drone stayed inside the hard geofence (the gust scenario
crosses it by design: there it must stay well short of the stop distance and end inside), that
the flight log is complete and readable to the end, and the one-line message the user sees.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from cfknode.app.cli import main
from cfknode.app.config import ConfigError, load_config
from cfknode.app.logs.writer import read_log
from cfknode.app.mission import FlightResult, run_flight
from cfknode.safety.estop_mailbox import live_flights


def scenario_path(name: str) -> Path:
    return Path(str(resources.files("cfknode").joinpath(f"scenarios/{name}.yaml")))


@dataclass(frozen=True)
class Expect:
    state: str  # the supervisor's final state
    cause: str
    message: str  # regular expression for the whole one-line message
    firmware: str = "landed"  # the simulated firmware's supervisor after the hand-back
    crosses_fence: bool = False


T = r"\d+\.\d\d s"
SCENARIOS: dict[str, Expect] = {
    "mocap_dropout_50ms": Expect("LANDED", "complete", r"flight complete: landed"),
    "mocap_dropout_300ms": Expect("LANDED", "mocap_lost", rf"landed: mocap lost \(no frame for 0\.10 s\) at {T}"),
    "mocap_dropout_2s": Expect("EMERGENCY", "mocap_lost",
                               rf"motors stopped: mocap lost \(no frame for 0\.50 s\) at {T}"),
    "radio_loss": Expect("LANDED", "link_silent", rf"landed: no answer on the radio link for 0\.2\d s at {T}"),
    "radio_lost": Expect("EMERGENCY", "link_lost",
                         rf"motors stopped: radio link lost \(Too many packets lost\) at {T}", firmware="locked"),
    "solver_failure": Expect("LANDED", "complete", r"flight complete: landed; the geometric fallback flew 120 ticks"),
    "nan_model": Expect("LANDED", "mpc_failure", rf"landed: the MPC failed for 0\.50 s \(nonfinite_input\) at {T}; "
                        r"the geometric fallback flew \d+ ticks"),
    "low_battery": Expect("LANDED", "battery_low", rf"landed: battery 3\.\d\d V below 3\.2 V at {T}"),
    "low_battery_idle": Expect("IDLE", "battery_low", r"take-off refused: battery 3\.5\d V is below 3\.7 V",
                               firmware="idle"),
    "geofence_wind": Expect("LANDED", "fence", rf"landed: crossed the geofence on x at {T}", crosses_fence=True),
    "heavy_payload": Expect("LANDED", "tracking", rf"landed: tracking error 0\.\d\d m above 0\.5 m at {T}"),
    "sigint": Expect("LANDED", "sigint", rf"landed: Ctrl-C \(SIGINT\) at {T}"),
    "sigint_twice": Expect("EMERGENCY", "sigint_stop", rf"motors stopped: second Ctrl-C \(SIGINT\) at {T}"),
}


def _cfg(tmp_path: Path, path: Path | None = None, **overrides):
    return load_config(path, overrides={"log.dir": str(tmp_path), "safety.estop_dir": str(tmp_path / "estop"),
                                        **overrides})


@pytest.fixture(scope="module")
def flights(tmp_path_factory) -> dict[str, FlightResult]:
    """Each scenario flown once, on demand."""
    cache: dict[str, FlightResult] = {}

    class Flights:
        def __getitem__(self, name: str) -> FlightResult:
            if name not in cache:
                tmp = tmp_path_factory.mktemp(name)
                cache[name] = run_flight(_cfg(tmp, scenario_path(name)), name_hint=name)
            return cache[name]

    return Flights()


def test_every_scenario_file_is_a_valid_config_overlay_and_is_tested():
    names = {p.stem for p in scenario_path("x").parent.glob("*.yaml")}
    assert names == set(SCENARIOS) | {"trainer_crash"}
    for name in names:
        load_config(scenario_path(name))


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_scenario(name, flights):
    expect = SCENARIOS[name]
    res = flights[name]
    extra = res.summary.extra
    outcome = res.outcome

    # End state, as the supervisor and the simulated drone see it.
    assert outcome.state.value == expect.state, outcome.message
    assert outcome.cause == expect.cause
    assert re.fullmatch(expect.message, outcome.message), outcome.message
    assert extra["outcome"] == outcome.message and extra["safety_state"] == expect.state
    after = extra["vehicle_after_shutdown"]
    assert after["on_ground"] and after["motors"] == [0, 0, 0, 0] and after["position"][2] == 0.0
    assert extra["firmware_after_shutdown"] == expect.firmware

    # Geofence.
    fence = load_config(scenario_path(name)).safety
    if expect.crosses_fence:
        assert 0.0 < extra["fence_excursion_m"] < 0.5 * fence.fence_stop_distance
        lo, hi = np.array(fence.fence_min), np.array(fence.fence_max)
        assert np.all(lo <= after["position"]) and np.all(np.array(after["position"]) <= hi)
        # Back inside by the fence brake, tilted past the MPC's limit but not past the brake's.
        commands = read_log(res.summary.log_path)
        pitch = np.abs(commands.array("/command", "pitch_deg"))
        assert "brake" in list(commands.array("/command", "source"))
        assert pitch.max() > load_config(scenario_path(name)).controller.max_tilt_deg + 5.0
        assert pitch.max() <= fence.fence_brake_tilt_deg + 1e-6
    else:
        assert extra["fence_excursion_m"] == 0.0

    # The flight log: complete, readable, and ending with what the user was told.
    log = read_log(res.summary.log_path)
    assert not log.truncated and log.note == ""
    ticks = log.topic("/tick")
    assert len(ticks) == res.record.ticks and ticks[-1]["t"] == pytest.approx(res.record.t[-1])
    assert log.topic("/summary")[-1]["extra"]["outcome"] == outcome.message
    assert log.topic("/safety")[-1]["state"] == expect.state
    transitions = [m for m in log.topic("/events") if m.get("source") == "supervisor" and "state" in m]
    assert transitions[-1]["state"] == expect.state

    # When the motors went off, and from where.
    t_cmd = log.times("/command")
    thrust = log.array("/command", "thrust")
    z_true = log.array("/state", "p_true")[:, 2] if log.topic("/state") else np.zeros(0)
    t_state = log.times("/state")
    if expect.state == "IDLE":
        assert np.all(thrust == 0) and res.record.p[:, 2].max() == 0.0
        return
    t_off = transitions[-1]["t"]
    assert np.all(thrust[t_cmd > t_off + 1e-9] == 0)
    z_at_off = float(np.interp(t_off, t_state, z_true))
    if expect.state == "EMERGENCY":
        assert z_at_off > 0.2  # stopped in the air, as asked: it did not land first
    else:
        assert z_at_off < 0.1  # cut at touchdown


# The scenarios' 3 s circle starts with a 1 s ramp: its largest error is there, 4.7 cm with the plain MPC and
# 5.1 cm with the fast layer (on by default), whose offset follows the start of the circle.
MAX_ERROR = 0.055  # m


def test_short_mocap_dropout_changes_nothing_but_the_frame_count(flights):
    res = flights["mocap_dropout_50ms"]
    assert res.summary.extra["mocap_dropouts"] == 5
    assert res.summary.extra["fallback_ticks"] == 0
    assert res.summary.max_error < MAX_ERROR


def test_solver_failure_is_flown_by_the_fallback_and_counted(flights):
    res = flights["solver_failure"]
    assert res.summary.extra["fallback_reasons"] == {"injected_failure": 120}
    assert res.record.fallbacks == 120 and res.summary.max_error < MAX_ERROR
    log = read_log(res.summary.log_path)
    assert list(log.array("/command", "source")).count("fallback") == 120
    assert [m.get("status") for m in log.topic("/tick")].count("injected_failure") == 120


def test_nan_model_falls_back_on_every_tick_after_the_swap(flights):
    res = flights["nan_model"]
    assert set(res.summary.extra["fallback_reasons"]) == {"nonfinite_input"}
    t = res.record.t
    flown = ~res.record.mpc_ok & (t >= 3.0) & (res.record.solve_s > 0)
    assert flown.sum() == res.record.fallbacks


def test_radio_loss_leaves_the_firmware_to_its_watchdog(flights):
    # The host's zeros never arrive: the firmware levelled out, then cut the motors and locked.
    assert flights["radio_lost"].summary.extra["firmware_after_shutdown"] == "locked"
    assert flights["radio_loss"].summary.extra["firmware_after_shutdown"] == "landed"


def test_trainer_crash(tmp_path):
    """The trainer dies in its third round: it is restarted, learning goes on, and the flight completes with the
    model it flies. Whether the gate accepts a round is the plant's business (on the realistic plant beside the
    fast layer it accepts none: docs/realistic-plant.md), so the restart is checked by the rounds decided."""
    res = run_flight(_cfg(tmp_path, scenario_path("trainer_crash")))
    assert res.outcome.state.value == "LANDED" and res.outcome.message == "flight complete: landed"
    extra = res.summary.extra
    assert extra["trainer_crashes"] == 1 and extra["trainer_restarts"] >= 1 and not extra["trainer_failed"]
    assert extra["models_trained"] >= 3  # rounds 1 and 2, and the restarted trainer's
    log = read_log(res.summary.log_path)
    assert not log.truncated
    events = [(m["t"], m["event"]) for m in log.topic("/model")]
    t_crash = next(t for t, e in events if e == "crash")
    t_restart = next(t for t, e in events if e == "restart")
    decided = [t for t, e in events if e in ("swap", "reject")]
    assert t_crash <= t_restart and any(t < t_crash for t in decided) and any(t > t_restart for t in decided)


def test_sigint_in_a_real_process(tmp_path):
    """`cfknode fly` with the scenario: the process sends itself SIGINT; it lands and says so."""
    cmd = [sys.executable, "-m", "cfknode", "fly", "--config", str(scenario_path("sigint")), "--json",
           "--log-dir", str(tmp_path), "--set", f"safety.estop_dir={tmp_path}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    # Landed safely, but the mission was cut short: exit status 1, and the outcome line on stderr.
    assert proc.returncode == 1, proc.stderr
    assert re.fullmatch("cfknode: " + SCENARIOS["sigint"].message, proc.stderr.strip().splitlines()[-1])
    summary = json.loads(proc.stdout)
    assert re.fullmatch(SCENARIOS["sigint"].message, summary["extra"]["outcome"])
    assert summary["extra"]["vehicle_after_shutdown"]["motors"] == [0, 0, 0, 0]
    assert not read_log(summary["log_path"]).truncated


def test_soft_fence_clamps_a_reference_that_leaves_the_box(tmp_path):
    # The 0.5 m circle in a fence whose soft box ends at x = 0.4 m: refused before take-off unless
    # forced; forced, it is flown clamped, never outside.
    with pytest.raises(ConfigError, match="reaches x = 0.50 m, beyond the fence's 0.40 m"):
        run_flight(_cfg(tmp_path, scenario_path("mocap_dropout_50ms"), **{
            "faults.mocap_outages": [], "safety.fence_max": [0.6, 1.5, 2.0]}))
    res = run_flight(_cfg(tmp_path, scenario_path("mocap_dropout_50ms"), **{
        "faults.mocap_outages": [], "safety.fence_max": [0.6, 1.5, 2.0], "hardware.force": True}))
    assert res.outcome.message == "flight complete: landed"
    assert res.record.p_ref[:, 0].max() == pytest.approx(0.4)
    assert res.summary.extra["fence_excursion_m"] == 0.0 and res.record.p[:, 0].max() < 0.6
    events = [m["text"] for m in read_log(res.summary.log_path).topic("/events")]
    assert "the reference leaves the geofence's soft box; it is clamped into it" in events


def test_estop_command_from_another_terminal_stops_a_flight(tmp_path):
    cfg = _cfg(tmp_path, None, **{"trajectory.kind": "hover", "trajectory.duration": 60.0})
    box = tmp_path / "estop"
    result: list[FlightResult] = []
    flight = threading.Thread(target=lambda: result.append(run_flight(cfg)))
    flight.start()
    try:
        deadline = time.monotonic() + 120
        while not live_flights(box) and flight.is_alive() and time.monotonic() < deadline:
            time.sleep(0.01)
        code = subprocess.run([sys.executable, "-m", "cfknode", "estop", "--dir", str(box),
                               "--robot", "sim-cf231", "--timeout", "30"], capture_output=True, text=True,
                              timeout=120)
    finally:
        flight.join(timeout=300)
    assert code.returncode == 0, code.stderr
    outcome = result[0].outcome
    assert outcome.state.value == "EMERGENCY" and outcome.cause == "estop_stop"
    assert outcome.message.startswith("motors stopped: cfknode estop --robot sim-cf231 at")
    assert live_flights(box) == []  # the flight withdrew its presence
    assert main(["estop", "--dir", str(box), "--robot", "sim-cf231"]) == 1


def test_fault_free_flight_is_unchanged_by_the_supervisor(tmp_path):
    short = {"trajectory.duration": 4.0, "trajectory.takeoff_duration": 2.0, "trajectory.settle_duration": 0.5,
             "trajectory.land_duration": 2.0, "trajectory.ramp_duration": 1.0, "sim.seed": 3}
    on = run_flight(_cfg(tmp_path, None, **short))
    off = run_flight(_cfg(tmp_path, None, **short, **{"safety.enabled": False}))
    assert on.outcome.message == off.outcome.message == "flight complete: landed"
    assert on.summary.mse == pytest.approx(off.summary.mse, rel=0.01)
    assert on.summary.ticks == off.summary.ticks


class Boom(BaseException):
    """Not an ``Exception``: the loop degrades on those (tests/test_tick_errors.py); this one
    escapes it, as an interpreter-level error would, and the hand-back must still run."""


class CrashAt:
    """A tick observer that raises mid-flight something the loop does not catch."""

    def __init__(self, t: float) -> None:
        self.t = t

    def on_tick(self, tick) -> None:
        if tick.t >= self.t:
            raise Boom(f"observer failed at {tick.t:.2f} s")


def test_a_crash_in_the_loop_still_hands_the_firmware_back_and_closes_the_log(tmp_path, monkeypatch):
    from cfknode.sim_backend import crazyflie

    sims = []
    original = crazyflie.SimCrazyflie.__init__

    def capture(self, *args, **kwargs):
        original(self, *args, **kwargs)
        sims.append(self)

    monkeypatch.setattr(crazyflie.SimCrazyflie, "__init__", capture)
    cfg = _cfg(tmp_path, scenario_path("mocap_dropout_50ms"), **{"faults.mocap_outages": []})
    with pytest.raises(Boom):
        run_flight(cfg, observers=[CrashAt(2.0)])
    sim = sims[0]
    fw = sim.firmware
    assert fw.last_setpoint.thrust == 0 and fw.motor_commands == (0, 0, 0, 0)
    sim.step_to(sim.t + 2.5)  # hand-back done right: the firmware lands, it does not lock
    assert fw.supervisor_state == "landed" and sim.vehicle.on_ground
    (path,) = tmp_path.glob("*.mcap")
    log = read_log(path)
    assert not log.truncated and log.times("/tick")[-1] == pytest.approx(2.0)


def test_a_late_mpc_answer_is_replaced_by_the_fallback():
    """On a wall clock a solve slower than safety.solve_deadline_s is stale: the fallback flies."""
    from types import SimpleNamespace

    from cfknode.flight.estimator import StateEstimate
    from cfknode.flight.geometric import GeometricGains, geometric_acc
    from cfknode.flight.controller import Controller
    from cfknode.flight.mpc import MpcSolution
    from cfknode.flight.trajectory import make_trajectory

    cfg = load_config()
    n = cfg.controller.horizon
    slow = MpcSolution(np.array([0.5, 0.0, 0.0]), True, "ok", 0.004, np.zeros((n + 1, 6)), np.zeros((n, 3)))
    solver = SimpleNamespace(solve=lambda x0, ref, residual=None: slow, backend="slow")
    ref = make_trajectory(cfg.trajectory, np.zeros(3)).sample(2.0 + cfg.controller.dt * np.arange(n + 1))
    est = StateEstimate(2.0, ref.p[0] + [0.05, 0.0, 0.0], np.zeros(3), np.array([1.0, 0, 0, 0]), 0.0)
    gains = GeometricGains.from_config(cfg.controller, cfg.vehicle)
    late = Controller(cfg.controller, cfg.vehicle, solver=solver, deadline_s=0.002).step(2.0, est, ref)
    assert (late.ok, late.source, late.status, late.solve_s) == (False, "fallback", "deadline", 0.004)
    np.testing.assert_allclose(late.acc, geometric_acc(est.p, est.v, ref.p[0], ref.v[0], ref.a[0], gains))
    lockstep = Controller(cfg.controller, cfg.vehicle, solver=solver, deadline_s=None).step(2.0, est, ref)
    assert (lockstep.ok, lockstep.source, lockstep.status) == (True, "mpc", "ok") and lockstep.acc[0] == 0.5


def test_the_fence_brake_flies_the_geometric_law_at_its_steeper_tilt():
    """The MPC's box stops at controller.max_tilt_deg; the brake a fence landing flies may tilt to its own."""
    from cfknode.flight.controller import Controller
    from cfknode.flight.estimator import StateEstimate
    from cfknode.flight.geometric import GeometricGains, geometric_acc
    from cfknode.flight.trajectory import make_trajectory

    cfg = load_config(overrides={"trajectory.kind": "hover"})
    n = cfg.controller.horizon
    ref = make_trajectory(cfg.trajectory, np.zeros(3)).sample(3.0 + cfg.controller.dt * np.arange(n + 1))
    est = StateEstimate(3.0, ref.p[0] + [0.3, 0.0, 0.0], np.array([0.8, 0.0, 0.0]), np.array([1.0, 0, 0, 0]), 0.0)
    usual = Controller(cfg.controller, cfg.vehicle, ground_z=0.0).step(3.0, est, ref, phase="LAND")
    brake = Controller(cfg.controller, cfg.vehicle, ground_z=0.0).step(3.0, est, ref, phase="LAND",
                                                                        brake_tilt_deg=45.0)
    assert usual.source == "mpc" and abs(usual.setpoint.pitch_deg) <= cfg.controller.max_tilt_deg + 1e-9
    assert (brake.source, brake.ok) == ("brake", True)
    assert cfg.controller.max_tilt_deg + 10.0 < abs(brake.setpoint.pitch_deg) <= 45.0 + 1e-9
    gains = GeometricGains.from_config(cfg.controller, cfg.vehicle)  # the layer's offset is 0 on its first tick
    np.testing.assert_allclose(brake.acc, geometric_acc(est.p, est.v, ref.p[0], ref.v[0], ref.a[0], gains))


def test_the_dashboards_e_stop_key_lands_through_the_supervisor_hook(tmp_path):
    supervisors = []

    class KeyAt:  # the dashboard's key reader, pressing space at 2.5 s
        def on_tick(self, tick) -> None:
            if tick.t >= 2.5 and tick.supervisor_state == "TRACK":
                supervisors[0].request_land()

    cfg = _cfg(tmp_path, scenario_path("mocap_dropout_50ms"), **{"faults.mocap_outages": []})
    res = run_flight(cfg, observers=[KeyAt()], on_supervisor=supervisors.append)
    assert res.outcome.state.value == "LANDED" and res.outcome.cause == "operator_land"
    assert re.fullmatch(r"landed: operator e-stop key at 2\.50 s", res.outcome.message)


# --- the injectors on their own (no flight) ---------------------------------------------------


def test_radio_blackout_loses_packets_in_its_window_and_the_link_after_100():
    from cfknode.app.config import FaultWindow
    from cfknode.sim_backend.crazyflie import SimCrazyflie
    from cfknode.sim_backend.faults import RadioBlackout

    sim = SimCrazyflie(load_config().vehicle, load_config().sim)
    firmware = sim.firmware
    short = RadioBlackout(sim, [FaultWindow(1.0, 0.3)])
    assert sim.firmware is not firmware and sim.firmware.step == firmware.step
    sim.firmware.on_rpyt(0.5, 0.0, 0.0, 0.0, 0)
    assert firmware.setpoints_received == 1
    for i in range(30):
        sim.firmware.on_rpyt(1.0 + 0.01 * i, 0.0, 0.0, 0.0, 0)
    assert firmware.setpoints_received == 1 and short.dropped == 30 and short.lost is None
    assert short.link_status(1.25).silence_s == pytest.approx(0.75)
    sim.firmware.on_extpose(1.35, (0, 0, 0), (0, 0, 0, 1))
    assert firmware.extposes_received == 1 and short.link_status(1.35).silence_s == 0.0

    sim2 = SimCrazyflie(load_config().vehicle, load_config().sim)
    long = RadioBlackout(sim2, [FaultWindow(1.0, 1.5)])
    for i in range(100):
        sim2.firmware.on_rpyt(1.0 + 0.005 * i, 0.0, 0.0, 0.0, 0)
    assert long.lost == "Too many packets lost" and long.link_status(3.0).lost == long.lost
    sim2.firmware.on_rpyt(5.0, 0.0, 0.0, 0.0, 0)  # after the window: the link is gone for good
    assert sim2.firmware.setpoints_received == 0


def test_gust_vehicle_blows_only_during_the_gust():
    from cfknode.app.config import Gust
    from cfknode.sim_backend.faults import GustVehicle

    cfg = load_config(overrides={"sim.drag": [0.03, 0.03, 0.03], "sim.initial_position": [0.0, 0.0, 1.0]})
    vehicle = GustVehicle(cfg.vehicle, cfg.sim, [Gust(0.01, 0.01, (4.0, 0.0, 0.0))])
    hover = [cfg.vehicle.mass * cfg.vehicle.gravity / 4 / cfg.vehicle.thrust_max_per_motor * 65535] * 4
    vehicle.reset([0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0], [cfg.vehicle.mass * cfg.vehicle.gravity / 4] * 4)
    vx = []
    for _ in range(15):
        vehicle.step(hover, cfg.vehicle.mass)
        vx.append(vehicle.state[3])
    assert vx[4] == pytest.approx(0.0, abs=1e-12)  # calm before 10 ms
    assert vx[9] > vx[5] > 0.0  # pushed along +x during the gust
    assert vx[14] < vx[10]  # drag slows it after


def test_failing_solver_and_nan_model():
    from cfknode.app.config import FaultWindow
    from cfknode.flight.mpc import MpcSolution
    from cfknode.sim_backend.faults import FailingSolver, NanResidual

    good = MpcSolution(np.ones(3), True, "ok", 1e-4, np.zeros((3, 6)), np.zeros((2, 3)))
    now = [0.0]
    solver = FailingSolver(type("M", (), {"solve": lambda self, x0, ref, residual=None: good})(),
                           [FaultWindow(1.0, 0.5)], lambda: now[0])
    assert solver.solve(None, None) is good
    now[0] = 1.2
    bad = solver.solve(None, None)
    assert not bad.ok and bad.status == "injected_failure" and np.all(bad.acc == 0) and np.isnan(bad.x_pred).all()
    c, jx, ju = NanResidual().linearise(np.zeros((20, 6)), np.zeros((20, 3)))
    assert np.isnan(c).all() and c.shape == (20, 3) and jx.shape == (20, 3, 6) and ju.shape == (20, 3, 3)


@pytest.mark.parametrize(
    ("overrides", "fragment"),
    [
        ({"faults.gusts": [{"t": 1.0, "duration": 1.0, "wind": [3.0, 0.0, 0.0]}]}, "needs 'sim.drag' > 0"),
        ({"faults.mocap_outages": [{"t": 1.0, "duration": 0.0}]}, "duration > 0"),
        ({"faults.nan_model_at": 2.0, "controller.kind": "geometric"}, "needs an MPC controller"),
    ],
)
def test_faults_that_cannot_be_injected_are_refused(overrides, fragment, tmp_path):
    from cfknode.app.config import ConfigError

    with pytest.raises(ConfigError, match=re.escape(fragment)):
        run_flight(_cfg(tmp_path, None, **overrides))
