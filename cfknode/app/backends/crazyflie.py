"""The hardware backend (``--backend cf``): a robot from the robots file, its mocap, its radio,
the pre-flight checks, and the flight clock; ``CrazyflieBackend`` is the counterpart of ``sim.SimulatorBackend``.

``hardware_backend(cfg)`` connects the mocap (``motioncapture``, with a deadline) and the
radio (cflib: parameters, telemetry, heartbeat), lets both stream for
``hardware.preflight_settle`` seconds while the mocap feeds the onboard estimator, runs the
pre-flight checks, and yields a ``HardwareBackend``; on the way out (any way out) the radio
hands the firmware back and the mocap is closed.

A robot whose URI is ``sim://N`` flies the simulator through exactly this code: the
simulator is registered behind cflib's ``sim://`` driver, stepped against the wall clock,
and serves the ``motioncapture`` object API (``SimulatedMotionCaptureClient``) to the same
reader thread a Vicon would feed. ``cf_session(cfg)`` picks the right one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterator

import numpy as np

from cfknode.app.config import Config, ConfigError
from cfknode.kernel.clock import WallClock
from cfknode.kernel.link import LinkStatus
from cfknode.safety.watchdogs import radio_link_status
from cfknode.app.backends.radio import CONTROLLER_PID, ESTIMATOR_KALMAN, HardwareRadio, LinkSafety, RadioError
from cfknode.app.backends.sim_mocap import SimulatedMotionCaptureClient
from cfknode.app.backends.stale_setpoint import StalePolicy
from cfknode.mocap.motioncapture_source import (
    Connector,
    MocapError,
    MotioncaptureSource,
)
from cfknode.app.backends.robots import Robot, load_robot
from cfknode.safety.preflight import PreflightError, PreflightReport, PreflightSnapshot, enforce, render_table, run_checks

# What a hardware session can fail with besides ConfigError; each message is one line.
HARDWARE_ERRORS = (MocapError, RadioError, PreflightError)
_MIN_FRAMES_BEFORE_RESET = 5  # extposes the onboard Kalman filter has seen before it is reset


@dataclass(frozen=True)
class HardwareBackend:
    robot: Robot
    config: Config  # the run's config with the robot's vehicle (mass, thrust mapping) and URI
    mocap: MotioncaptureSource
    radio: HardwareRadio
    clock: WallClock  # the flight clock: zero when the backend is handed over
    preflight: PreflightReport
    start_position: np.ndarray  # measured at the pre-flight: where the take-off starts
    truth: Callable[[], np.ndarray] | None = None  # the simulator's true state (sim:// only)
    sim: Any = None  # the SimCrazyflie (sim:// only)


def robot_for(cfg: Config) -> Robot:
    """The configured robot (``hardware.robot`` in ``hardware.robots_file``, "" = the example)."""
    return load_robot(cfg.hardware.robots_file or None, cfg.hardware.robot)


def flight_config(cfg: Config, robot: Robot) -> Config:
    """``cfg`` with the robot's mass and thrust mapping, its URI, and its type's battery limits
    for the supervisor (refuse take-off below ``voltage_critical``, land below ``voltage_land``)."""
    return dataclasses.replace(
        cfg,
        vehicle=robot.vehicle(cfg.vehicle),
        radio=dataclasses.replace(cfg.radio, uri=robot.uri),
        safety=dataclasses.replace(cfg.safety, battery_takeoff_min_v=robot.battery.voltage_critical,
                                   battery_land_v=robot.battery.voltage_land),
    )


def firmware_params(cfg: Config, robot: Robot) -> dict[str, float]:
    """What the radio sets at connect: the stack's needs first, then the robot file's own."""
    params: dict[str, float] = {
        "stabilizer.estimator": ESTIMATOR_KALMAN,
        "stabilizer.controller": CONTROLLER_PID,
        "locSrv.extPosStdDev": cfg.hardware.extpos_std,
        "locSrv.extQuatStdDev": cfg.hardware.extquat_std,
    }
    params.update(robot.firmware_params)
    return params


def _rw_cache(cfg: Config) -> str:
    if cfg.hardware.rw_cache:
        return cfg.hardware.rw_cache
    from cfknode.flight.mpc_codegen import default_cache_dir

    path = default_cache_dir() / "cflib"
    path.mkdir(parents=True, exist_ok=True)
    return str(path)


@contextlib.contextmanager
def hardware_backend(
    cfg: Config,
    *,
    robot: Robot | None = None,
    connect: Connector | None = None,
    console: Any = None,
) -> Iterator[HardwareBackend]:
    """Connect mocap and radio, run the pre-flight checks, yield; always hand the drone back.

    ``connect`` replaces ``motioncapture.connect`` (tests, the simulator); ``console`` (a rich
    Console) gets the pre-flight table, passed or not. Raises one of ``HARDWARE_ERRORS``.
    """
    robot = robot if robot is not None else robot_for(cfg)
    hw = cfg.hardware
    if not robot.enabled:
        raise ConfigError(f"robot {robot.name!r} is disabled in {robot.source} (enabled: false)")
    mocap = MotioncaptureSource.open(
        hw.mocap_type, hw.mocap_host, robot.name,
        timeout=hw.mocap_connect_timeout,
        connect=connect,
        expected_rate_hz=hw.mocap_rate_hz,
        mock_bodies={robot.name: (*robot.initial_position, 1.0, 0.0, 0.0, 0.0)},
    )
    try:
        with connect_robot(cfg, robot, mocap, console=console) as link:
            clock = WallClock()
            mocap.set_time_base(clock.now)
            link.radio.set_clock(clock.now)
            yield HardwareBackend(
                robot=robot, config=flight_config(cfg, robot), mocap=mocap, radio=link.radio, clock=clock,
                preflight=link.preflight, start_position=link.start_position,
            )
    finally:
        mocap.close()


@dataclass(frozen=True)
class RobotLink:
    """A robot connected and checked, not yet on a flight clock."""

    radio: HardwareRadio
    preflight: PreflightReport
    start_position: np.ndarray  # measured at the pre-flight: where the take-off starts


@contextlib.contextmanager
def connect_robot(cfg: Config, robot: Robot, mocap: MotioncaptureSource, *, console: Any = None) -> Iterator[RobotLink]:
    """Connect ``robot``'s radio, feed it ``mocap``'s frames, run its pre-flight checks, yield;
    always hand the drone back. ``mocap`` reads this robot's rigid body (its own connection or a
    shared one: mocap/shared_source.py). Raises one of ``HARDWARE_ERRORS``."""
    hw = cfg.hardware
    radio: HardwareRadio | None = None
    try:
        radio = HardwareRadio(
            robot.uri,
            tx_rate_hz=cfg.radio.tx_rate_hz,
            lockstep=False,
            rw_cache=_rw_cache(cfg),
            params=firmware_params(cfg, robot),
            telemetry_hz=hw.telemetry_hz,
            reboot_after_heartbeat=hw.reboot_after_heartbeat,
            imu_log=cfg.radio.imu_log,
            safety=LinkSafety(heartbeat_hz=hw.heartbeat_hz,
                              stale=StalePolicy(cfg.radio.stale_hold_slots, cfg.radio.stale_stop_s)),
        )
        radio.connect(hw.radio_connect_timeout)
        settle_until = time.monotonic() + hw.preflight_settle
        # Every frame goes to the onboard Kalman filter from now on, straight from the mocap thread.
        mocap.set_pose_listener(lambda pose: radio.feed_extpose(pose.position, pose.quaternion))
        if mocap.wait_for_frames(mocap.status().frames + _MIN_FRAMES_BEFORE_RESET, hw.preflight_settle):
            radio.reset_estimator(timeout=hw.radio_connect_timeout)
        radio.wait_for_telemetry(max(settle_until - time.monotonic(), 0.0))
        time.sleep(max(settle_until - time.monotonic(), 0.0))
        report = run_checks(_snapshot(cfg, robot, radio, mocap))
        if console is not None:
            console.print(render_table(report, title=f"Pre-flight checks: {robot.name} ({robot.uri})"))
        report = enforce(report, hw.force)
        latest = mocap.status().latest
        start = np.array(latest.position if latest is not None else robot.initial_position, dtype=float)
        yield RobotLink(radio=radio, preflight=report, start_position=start)
    finally:
        if radio is not None:
            radio.shutdown()
        mocap.set_pose_listener(None)  # a shared mocap streams on: no extposes to a drone handed back


def _snapshot(cfg: Config, robot: Robot, radio: HardwareRadio, mocap: MotioncaptureSource) -> PreflightSnapshot:
    telemetry = radio.telemetry()
    link = radio.link_statistics()
    status = mocap.status()
    latest = status.latest
    return PreflightSnapshot(
        robot=robot.name,
        link_up=radio.cf is not None and link.link_lost is None,
        link_error=link.link_lost,
        latency_ms=link.latency_ms,
        protocol_version=radio.protocol_version,
        vbat=telemetry.vbat if telemetry else None,
        pm_state=telemetry.pm_state if telemetry else None,
        voltage_warning=robot.battery.voltage_warning,
        voltage_critical=robot.battery.voltage_critical,
        supervisor_info=telemetry.supervisor_info if telemetry else None,
        mocap_label=mocap.label,
        mocap_rate_hz=status.body_rate_hz,
        expected_rate_hz=cfg.hardware.mocap_rate_hz,
        mocap_error=status.error,
        body_seen_age=status.last_seen_age,
        body_position=tuple(latest.position.tolist()) if latest is not None else None,
        body_quaternion=tuple(latest.quaternion.tolist()) if latest is not None else None,
        initial_position=robot.initial_position,
        position_tolerance=cfg.hardware.preflight_position_tolerance,
        max_tilt_deg=cfg.hardware.preflight_max_tilt_deg,
        heartbeat_requested=cfg.hardware.heartbeat_hz > 0,
    )


# --- the simulator behind the hardware path ------------------------------------------------------


@dataclass(frozen=True)
class SimulatedHardware:
    sim: Any  # SimCrazyflie
    connect: Connector  # a motioncapture.connect stand-in serving the simulator's poses
    clock: WallClock  # the simulator's own wall clock (the drone's time, not the flight's)


@contextlib.contextmanager
def simulated_hardware(cfg: Config, robot: Robot) -> Iterator[SimulatedHardware]:
    """A simulated Crazyflie at ``robot.uri`` (``sim://N``), stepped in real time.

    The simulator's physics is ``cfg.vehicle`` (and ``cfg.sim``'s scenario), while the flight
    stack believes the robots file, as with a real drone; it starts at the robot's
    ``initial_position``. Mocap noise, latency and dropouts come from ``cfg.sim``.
    """
    from cfknode.sim_backend.crazyflie import SimCrazyflie
    from cfknode.sim_backend.link_driver import register_simulator, unregister_simulator
    from cfknode.sim_backend.realtime import RealtimeStepper

    if not robot.uri.startswith("sim://"):
        raise ConfigError(f"robot {robot.name!r} has URI {robot.uri!r}, not a sim:// URI")
    sim_cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, initial_position=robot.initial_position,
                                                               realtime=True))
    sim = SimCrazyflie(sim_cfg.vehicle, sim_cfg.sim)
    register_simulator(robot.uri, sim)
    clock = WallClock()
    stepper = RealtimeStepper(sim, clock.now).start()
    served: list[SimulatedMotionCaptureClient] = []

    def connect(mocap_type: str, mocap_cfg: dict[str, str]) -> SimulatedMotionCaptureClient:
        s = cfg.sim
        mc = SimulatedMotionCaptureClient(
            {robot.name: sim}, rate_hz=cfg.hardware.mocap_rate_hz, position_noise=s.mocap_position_noise,
            attitude_noise=s.mocap_attitude_noise, latency=s.mocap_latency, dropout_prob=s.mocap_dropout_prob,
            seed=s.seed, frame_time=clock.monotonic,  # the simulator's time is this clock's (the stepper's)
        )
        served.append(mc)
        return mc

    try:
        yield SimulatedHardware(sim=sim, connect=connect, clock=clock)
    finally:
        stepper.stop()
        for mc in served:
            mc.close()
        unregister_simulator(robot.uri)


@contextlib.contextmanager
def cf_session(cfg: Config, *, console: Any = None) -> Iterator[HardwareBackend]:
    """``--backend cf``: the configured robot, real or (``sim://``) simulated, ready to fly."""
    robot = robot_for(cfg)
    if not robot.uri.startswith("sim://"):
        with hardware_backend(cfg, robot=robot, console=console) as hw:
            yield hw
        return
    # The simulator stands in for the mocap system too: whatever type is configured, its
    # frames come through the same reader thread (as the "mock" type, which needs no host).
    sim_cfg = dataclasses.replace(cfg, hardware=dataclasses.replace(cfg.hardware, mocap_type="mock"))
    with simulated_hardware(cfg, robot) as simhw:
        with hardware_backend(sim_cfg, robot=robot, connect=simhw.connect, console=console) as hw:
            yield dataclasses.replace(hw, config=dataclasses.replace(hw.config, hardware=cfg.hardware),
                                      truth=lambda: simhw.sim.state, sim=simhw.sim)


class CrazyflieBackend:
    """``Backend`` for ``--backend cf``: a connected, checked robot (``HardwareBackend``) as the flight sees it.

    Open it with ``CrazyflieBackend.open(cfg)``; a ``sim://`` robot flies the simulator through
    the same adapters (``cf_session``)."""

    def __init__(self, hw: HardwareBackend) -> None:
        self.hw = hw
        self.config, self.clock, self.mocap, self.radio = hw.config, hw.clock, hw.mocap, hw.radio
        self.start_position = hw.start_position
        self.events = tuple(hw.preflight.events())
        self.imu = hw.radio.imu  # the accelerometer log block; None if off or the firmware lacks it
        if hw.radio.imu_note is not None:
            self.events += ({"level": "warning", "text": hw.radio.imu_note, "source": "radio"},)
        self._link = radio_link_status(hw.radio)

    @classmethod
    @contextlib.contextmanager
    def open(cls, cfg: Config, console: Any = None) -> Iterator["CrazyflieBackend"]:
        from rich.console import Console

        with cf_session(cfg, console=console or Console(stderr=True)) as hw:
            yield cls(hw)

    def truth(self) -> np.ndarray | None:
        return self.hw.truth() if self.hw.truth is not None else None

    def true_mass(self) -> float | None:
        return None  # the mass a real vehicle carries is not known

    def battery_voltage(self) -> float | None:
        telemetry = self.hw.radio.telemetry()
        return telemetry.vbat if telemetry is not None else None

    def link_status(self, now: float) -> LinkStatus:
        return self._link(now)

    def wrap_solver(self, solver: Any) -> Any:
        return solver  # no injected faults on this path

    def fault_observers(self, model: Any) -> list[Any]:
        return []

    def after_handback(self) -> dict[str, Any]:
        extra: dict[str, Any] = {"preflight": self.hw.preflight.to_dict(), "handback": self.hw.radio.handback_note}
        if self.hw.sim is not None:
            extra["firmware_after_shutdown"] = self.hw.sim.firmware.supervisor_state
        return extra


def describe(hw: HardwareBackend) -> str:
    """One line for the console: robot, link, mocap."""
    return (f"{hw.robot.name} at {hw.robot.uri}, mocap {hw.mocap.label}, firmware protocol "
            f"{hw.radio.protocol_version}, heartbeat {'on' if hw.radio.heartbeat_enabled else 'off'}")


__all__ = [
    "CrazyflieBackend", "HARDWARE_ERRORS", "HardwareBackend", "RobotLink", "SimulatedHardware",
    "cf_session", "connect_robot", "describe", "firmware_params", "flight_config", "hardware_backend", "robot_for",
    "simulated_hardware",
]
