"""--backend cf against the simulator: the real adapter threads (cflib radio, motioncapture reader,
pre-flight checks) end to end, on the wall clock, with the simulator behind sim://."""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import shutil
import threading
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from rich.console import Console

from cfknode.app.config import Config, ConfigError, load_config
from cfknode.flight.controller import Controller
from cfknode.flight.estimator import VelocityEstimator
from cfknode.app.logs.writer import FlightLog, read_log
from cfknode.flight.loop import FlightParts, fly
from cfknode.app.backends.radio import RadioError
from cfknode.flight.trajectory import make_trajectory
from cfknode.app.backends.crazyflie import cf_session, flight_config, hardware_backend, robot_for, simulated_hardware
from cfknode.app.mission import build_controller, build_supervisor
from cfknode.mocap.motioncapture_source import MocapError
from cfknode.app.backends.robots import example_robots_path, load_robot
from cfknode.safety.preflight import PreflightError
from cfknode.safety.supervisor import State, SupervisorInputs
from cfknode.safety.watchdogs import radio_link_status

_uris = itertools.count(9500)

SHORT_HOVER = {
    "trajectory.kind": "hover",
    "trajectory.height": 0.4,
    "trajectory.duration": 1.5,
    "trajectory.takeoff_duration": 1.0,
    "trajectory.settle_duration": 0.3,
    "trajectory.land_duration": 1.0,
    "hardware.preflight_settle": 0.5,
    # A shared, loaded machine can stall a wall-clock simulator for a moment; these tests are
    # about the adapters, so the supervisor's mocap-loss reaction is given more slack.
    "safety.mocap_hold_s": 0.5,
    "safety.mocap_stop_s": 1.0,
}


def robots_file(tmp_path: Path) -> tuple[Path, str]:
    """A copy of the example robots file whose simulated robot has a URI of its own."""
    uri = f"sim://{next(_uris)}"
    path = tmp_path / "robots.yaml"
    shutil.copy(example_robots_path(), path)
    path.write_text(path.read_text().replace("uri: sim://0", f"uri: {uri}"))
    return path, uri


def cf_config(tmp_path: Path, **overrides: Any) -> Config:
    path, _ = robots_file(tmp_path)
    return load_config(overrides={"backend": "cf", "hardware.robot": "cf_sim", "hardware.robots_file": str(path),
                                  "log.dir": str(tmp_path), **SHORT_HOVER, **overrides})


def fly_cf(cfg: Config, name_hint: str, inspect: Any = None, flying: threading.Event | None = None) -> Any:
    """The ``--backend cf`` branch of a mission: the same wiring as the simulator's, with the
    hardware session's robot config, clock, mocap and radio. ``inspect(hw)`` runs in the session;
    ``flying`` is set while the flight loop runs."""
    mpc = build_controller(flight_config(cfg, robot_for(cfg)))  # the robot's limits; built before the clock starts
    with cf_session(cfg) as hw:
        flight_cfg = hw.config
        trajectory = make_trajectory(flight_cfg.trajectory, hw.start_position)
        with FlightLog.create(flight_cfg.log.dir, flight_cfg.to_dict(), "test", name_hint) as log:
            for event in hw.preflight.events():
                log.write("/events", 0.0, event)
            supervisor = build_supervisor(
                flight_cfg, hw.radio, trajectory=trajectory, log=log, deadlines_apply=True,
                inputs=SupervisorInputs(
                    battery_voltage=lambda: (hw.radio.telemetry() or SimpleNamespace(vbat=None)).vbat,
                    link_status=radio_link_status(hw.radio),
                ),
            )
            parts = FlightParts(
                clock=hw.clock, mocap=hw.mocap, estimator=VelocityEstimator(flight_cfg.estimator),
                trajectory=trajectory, supervisor=supervisor, log=log, truth=hw.truth,
                controller=Controller(flight_cfg.controller, flight_cfg.vehicle, solver=mpc,
                                      deadline_s=flight_cfg.safety.solve_deadline_s),
            )
            if flying is not None:
                flying.set()
            record = asyncio.run(fly(parts))
            if flying is not None:
                flying.clear()
            extra = inspect(hw) if inspect is not None else None
        return SimpleNamespace(record=record, outcome=supervisor.outcome(), hw=hw, extra=extra,
                               summary=SimpleNamespace(log_path=log.path))


def test_a_cf_flight_against_the_simulator_runs_the_real_adapters(tmp_path: Path) -> None:
    cfg = cf_config(tmp_path)
    flying = threading.Event()
    senders: list[tuple[str, int, bool]] = []  # firmware input, sending thread, during the flight

    def inspect(hw: Any) -> dict[str, Any]:
        from cfknode.sim_backend.link_driver import PARAM_TOC, _registry

        params = dict(zip((f"{p.group}.{p.name}" for p in PARAM_TOC), _registry[hw.robot.uri].param_values))
        return {"params": params, "heartbeats_received": hw.sim.firmware.estop_watchdog_notifications,
                "radio": hw.radio.stats(), "link": hw.radio.link_statistics(), "telemetry": hw.radio.telemetry(),
                "mocap": hw.mocap.status()}

    # Record which thread hands each packet to the simulated firmware (the sim:// driver
    # decodes in the sender's thread).
    from cfknode.sim_backend.firmware import Firmware

    on_rpyt, on_extpose = Firmware.on_rpyt, Firmware.on_extpose

    def rec_rpyt(self: Any, *args: Any) -> None:
        senders.append(("rpyt", threading.get_ident(), flying.is_set()))
        on_rpyt(self, *args)

    def rec_extpose(self: Any, *args: Any) -> None:
        senders.append(("extpose", threading.get_ident(), flying.is_set()))
        on_extpose(self, *args)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Firmware, "on_rpyt", rec_rpyt)
        mp.setattr(Firmware, "on_extpose", rec_extpose)
        result = fly_cf(cfg, "cf-e2e", inspect, flying)

    hw, info, rec = result.hw, result.extra, result.record
    # Pre-flight passed on the simulator's real telemetry and mocap.
    assert hw.preflight.ok and not hw.preflight.forced
    assert {r.name for r in hw.preflight.results} >= {"link", "battery", "mocap rate", "rigid body", "supervisor"}
    # It flew the hover and landed, on the robot file's mass.
    assert result.outcome.state is State.LANDED, result.outcome.message
    assert hw.config.vehicle.mass == load_robot(cfg.hardware.robots_file, "cf_sim").mass
    hover = (rec.t > 1.6) & (rec.t < 2.7)
    assert np.abs(rec.p[hover] - rec.p_ref[hover]).max() < 0.05
    assert rec.p[hover, 2].mean() == pytest.approx(0.4, abs=0.03)
    # The parameters the stack needs were set, and confirmed.
    assert info["params"]["stabilizer.estimator"] == 2 and info["params"]["stabilizer.controller"] == 1
    assert info["params"]["locSrv.extPosStdDev"] == pytest.approx(cfg.hardware.extpos_std)
    # Mocap frames went through the reader thread and on to the drone as extposes at the mocap rate.
    flight_s = float(rec.t[-1])
    assert info["mocap"].frames >= 0.9 * 100 * flight_s and info["mocap"].dropouts == 0
    assert info["radio"].extposes_sent >= 0.95 * info["mocap"].frames
    assert info["radio"].send_errors == 0 and info["radio"].link_lost is None
    # Heartbeat, telemetry and link statistics flowed.
    assert info["radio"].heartbeats_sent >= 4 * flight_s and info["heartbeats_received"] == info["radio"].heartbeats_sent
    assert info["telemetry"].samples >= 5 * flight_s and info["telemetry"].vbat > 3.7
    assert info["link"].link_quality == 100.0 and info["link"].latency_ms is not None
    # cflib never ran on the event loop's thread (asyncio.run runs on this one) during the flight.
    in_flight = [(name, tid) for name, tid, during in senders if during]
    assert {name for name, _ in in_flight} == {"rpyt", "extpose"}
    assert all(tid != threading.get_ident() for _, tid in in_flight)
    # Handed back: commander released to the stopped HL planner, then the reboot clears the
    # armed emergency-stop watchdog: nothing is left Locked.
    fw = hw.sim.firmware
    assert fw.boots == 2 and fw.supervisor_state == "idle" and fw.lock_reason is None
    assert hw.radio.handback_note is None
    assert not any(t.name.startswith(("radio-tx", "mocap-reader", "sim-realtime")) and t.is_alive()
                   for t in threading.enumerate())
    log = read_log(result.summary.log_path)
    assert len(log.topic("/mocap")) >= 0.9 * 100 * flight_s  # the pre-flight's frames are not in the log
    assert not [e for e in log.topic("/events") if e.get("source") == "preflight"]  # nothing to report


def test_a_failed_preflight_refuses_take_off_and_hands_the_drone_back(tmp_path: Path) -> None:
    cfg = cf_config(tmp_path, **{"hardware.heartbeat_hz": 0.0, "hardware.mocap_type": "mock"})
    robot = robot_for(cfg)
    elsewhere = dataclasses.replace(robot, initial_position=(0.5, 0.0, 0.0))
    console = Console(width=160, record=True)
    with simulated_hardware(cfg, robot) as simhw:  # the drone sits at the origin...
        with pytest.raises(PreflightError) as info:
            with hardware_backend(cfg, robot=elsewhere, connect=simhw.connect, console=console):
                pytest.fail("the backend must not be handed over")  # ...the robots file says 0.5 m away
        fw = simhw.sim.firmware
        assert not fw.thrust_locked and fw.setpoints_received >= 2  # connected, unlocked, zeros sent
        assert fw.setpoint.source in ("high_level", "rpyt") and fw.supervisor_state == "idle"
    message = str(info.value)
    assert "\n" not in message
    assert "rigid body: cf_sim is 0.50 m from its initial_position (tolerance 0.1 m)" in message
    assert [r.name for r in info.value.report.failures] == ["rigid body"]
    text = console.export_text()
    assert "Pre-flight checks: cf_sim" in text and "FAIL" in text


def test_force_overrides_a_failed_check_and_says_so(tmp_path: Path) -> None:
    cfg = cf_config(tmp_path, **{"hardware.heartbeat_hz": 0.0, "hardware.force": True,
                                 "sim.battery_voltage": 3.6})  # below the type's 3.7 V
    with cf_session(cfg) as hw:
        report = hw.preflight
        assert report.forced and [r.name for r in report.failures] == ["battery"]
        assert report.events()[-1]["text"].startswith("take-off FORCED despite: battery: 3.")
        assert hw.clock.now() < 0.5  # the flight clock starts at the hand-over


def test_mocap_that_never_answers_fails_before_the_radio_connects(tmp_path: Path) -> None:
    cfg = cf_config(tmp_path, **{"hardware.mocap_type": "vicon", "hardware.mocap_host": "10.9.9.9",
                                 "hardware.mocap_connect_timeout": 0.3})
    robot = robot_for(cfg)
    with simulated_hardware(cfg, robot) as simhw:
        hang = threading.Event()
        with pytest.raises(MocapError, match=r"^no answer from vicon at 10\.9\.9\.9 within 0\.3 s"):
            with hardware_backend(cfg, robot=robot, connect=lambda t, c: hang.wait()):
                pass
        hang.set()
        assert simhw.sim.firmware.setpoints_received == 0  # the radio was never opened


def test_a_missing_radio_closes_the_mocap(tmp_path: Path) -> None:
    cfg = cf_config(tmp_path, **{"hardware.mocap_type": "mock"})
    robot = robot_for(cfg)  # its sim:// URI has no simulator behind it
    with pytest.raises(RadioError, match=f"could not connect to {robot.uri}: .*no simulator registered"):
        with hardware_backend(cfg, robot=robot):
            pass
    assert not any(t.name.startswith("mocap-reader") and t.is_alive() for t in threading.enumerate())


def test_a_disabled_robot_is_refused(tmp_path: Path) -> None:
    cfg = cf_config(tmp_path, **{"hardware.robot": "cf5"})
    with pytest.raises(ConfigError, match="robot 'cf5' is disabled"):
        with cf_session(cfg):
            pass


def test_run_flight_with_backend_cf_against_the_simulator(tmp_path: Path) -> None:
    """`cfknode fly --backend cf` takes the same mission path as the simulator: run_flight end to end."""
    from cfknode.app.mission import run_flight

    res = run_flight(cf_config(tmp_path), name_hint="cf-run-flight")
    # A loaded machine may push a few wall-clock solves past their deadline: the fallback flies those.
    assert res.outcome.message.startswith("flight complete: landed"), res.outcome.message
    extra = res.summary.extra
    assert extra["backend"] == "cf" and not extra["lockstep"]
    assert extra["preflight"]["ok"], extra["preflight"]
    assert extra["firmware_after_shutdown"] != "locked"
    assert res.summary.max_error < 0.1
    # The accelerometer block through HardwareRadio: samples on the wall flight clock, never after the tick.
    from cfknode.app.logs.writer import read_log

    log = read_log(res.summary.log_path)
    t, imu_t = log.times("/state"), log.array("/state", "imu_t")
    seen = np.isfinite(imu_t)
    assert extra["imu_samples"] > 100 and seen.mean() > 0.9
    assert np.all(imu_t[seen] <= t[seen] + 5e-4)
