"""The application's configuration schema: the root ``Config`` and the sections only the application uses.

The other layers declare their own sections (``cfknode.flight.settings``, ``cfknode.safety.settings``,
...); ``cfknode.app.config`` fills all of them from YAML, and ``cfknode.app.config_bounds`` checks
them. Both import this module, which imports neither, so the schema sits below the two.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal

from cfknode.app.fleet.settings import FleetConfig
from cfknode.flight.settings import ControllerConfig, EstimatorConfig, TrajectoryConfig
from cfknode.kernel.setting import setting
from cfknode.kernel.vehicle import VehicleConfig
from cfknode.models.settings import FaultInjection, KnodeConfig, TrainingConfig
from cfknode.safety.settings import SafetyConfig
from cfknode.sim_backend.settings import FaultsConfig, SimConfig

__all__ = ["Config", "DashboardConfig", "HardwareConfig", "LogConfig", "OnlineConfig", "RadioConfig"]

@dataclass(frozen=True)
class OnlineConfig:
    enabled: bool = setting(doc="learn the residual in flight (`cfknode fly --online`)")
    t_col: float = setting(unit="s", low=0.05, high=60,
        doc="per training window (docs/history.md#online-learnings-keys)")
    epochs: int = setting(low=1, high=10000,
        doc="Adam steps per round; warm-started nets need few (the paper: 80 from scratch)")
    method: Literal["rk4", "euler", "dopri5"] = setting(doc="per-pair integration in a round: rk4 | euler | dopri5")
    lr: float = setting(low=0, high=1, open_low=True, doc="the paper's online learning rate")
    weight_decay: float = setting(low=0, high=100, doc="L2 on the new net, in training's units")
    warm_start: bool = setting(
        doc="start the new net from the newest (function kept, normalisation refitted); false: fresh")
    replay_windows: int = setting(low=0, high=20,
        doc="also train on this many recent earlier windows (0: the newest window only, as the paper)")
    paper_lockstep: bool = setting(
        doc="the paper's code: the simulation waits for every model, applied at once (reproduction only)")
    gate: bool = setting(doc="validation gate: finite, bounded, and better than the flying model on fresh data")
    gate_min_pairs: int = setting(low=2, high=100000,
        doc="fresh samples (recorded after the training window) the gate needs to judge")
    gate_control_gain: tuple[float, float] = setting(low=0, high=100, open_low=True,
        doc="eigenvalues of sym(I + dr/du) on the whole input box (mass factor 4x .. 0.25x)")
    gate_max_velocity_gain: float = setting(unit="1/s", low=0, high=100,
        doc="largest eigenvalue of sym(dr/dv) allowed (a positive one is a phantom instability)")
    gate_max_cross_gain: float = setting(low=0, high=10,
        doc="largest |dr_i/du_j|, i != j: mass and thrust errors scale each axis alike (see GateLimits)")
    gate_max_tilt_climb: float = setting(unit="m/s^2", low=0, high=10,
        doc="most climb a model may predict from tilting either way at the top of the input box")
    gate_layer_margin: float = setting(low=0, high=1, open_high=True,
        doc="beside a fast layer: a candidate must be this fraction better, constants aside,")
    gate_layer_steps: int = setting(unit="pairs", low=1, high=400,
        doc="... over this many consecutive fresh samples flown from each start")
    gate_layer_min_gain: float = setting(unit="m/s^2", low=0, high=10,
        doc="... and better by at least this acceleration over that rollout")
    gate_layer_min_score: float = setting(low=0, high=1, open_high=True,
        doc="... and remove more than this share of what the layer leaves on some axis (0: any); "
            "it flies on those axes only")
    gate_layer_horizontal_gain: tuple[float, float] = setting(low=0, high=100, open_low=True,
        doc="beside a fast layer: eigenvalues of sym(I + dr/du) over the horizontal commands (the layer has the mass)")
    gate_layer_velocity_coupling: float | None = setting(unit="1/s", low=0, high=100,
        doc="beside a fast layer: largest |dr_i/dv_j|, i != j (a vertical force from horizontal speed); null: any")
    gate_layer_rejudge: bool = setting(
        doc="beside a fast layer: score the flying model on later rounds' fresh data; stop flying axes it stops earning on")
    gate_layer_climb_feedback: float | None = setting(unit="1/s", low=0, high=100,
        doc="beside a fast layer: largest dr_z/dv_z (a force growing with climb rate is the motors' lag); null: any")
    gate_layer_min_pairs: int = setting(low=2, high=100000,
        doc="beside a fast layer: gate_min_pairs")
    layer_replay_windows: int = setting(low=0, high=40,
        doc="beside a fast layer: replay_windows")
    layer_weight_decay: float = setting(low=0, high=100, doc="beside a fast layer: weight_decay")
    layer_filter_hz: float = setting(unit="Hz", low=0.5, high=100,
        doc="beside a fast layer: the velocity low-pass of training and gate (training.velocity_filter_hz otherwise)")
    layer_command_lag_s: tuple[float, float] = setting(unit="s", low=0, high=0.5,
        doc="beside a fast layer: command_lag_s")
    layer_input_bounds: bool = setting(
        doc="beside a fast layer: each network is held to the range of its training data (models/input_bounds.py)")
    layer_attitude_lag: bool = setting(
        doc="beside a fast layer: identify the attitude loop's lag in flight and plan across it (docs/design.md#attitude-lag)")
    attitude_lag_span_s: float = setting(unit="s", low=0.25, high=30, doc="s of tracking per fit of the attitude lag")
    attitude_lag_min_fit: float = setting(low=0, high=1, doc="R^2 of the tilt a fit of the lag needs to be flown")
    attitude_lag_horizon: float = setting(low=0, high=2,
        doc="the MPC plans this times the identified lag ahead (estimator.command_delay)")
    trainer_timeout: float = setting(unit="s", low=0, high=600, open_low=True,
        doc="wall s without a result: the trainer is killed and restarted")
    trainer_start_timeout: float = setting(unit="s", low=1, high=3600,
        doc="wall s the trainer may take to come up (2-5 s unloaded) before the flight refuses to start")
    max_restarts: int = setting(low=0, high=100,
        doc="then online learning stops and the flight goes on with the last good model")
    trainer_nice: int = setting(low=0, high=19,
        doc="on a wall clock the trainer runs this much nicer than the flight (its deadlines come first)")
    start_time: float = setting(unit="s", low=0, high=3600,
        doc="collect from this flight time on (0: from take-off; no knowledge of disturbance times)")
    rollback_ticks: int = setting(unit="ticks", low=1, high=100000,
        doc="ticks watched after a swap (0.1 s at 400 Hz) ...")
    rollback_fallbacks: int = setting(low=1, high=100000, doc="... this many MPC fallbacks in them roll the model back")
    monitor: bool = setting(
        doc="drop the flying model for nominal when it explains the newest motion worse than nominal")
    monitor_window_s: float = setting(unit="s", low=0, high=2, open_low=True,
        doc="s of newest ticks judged: the mean acceleration error of the model vs nominal")
    monitor_every_ticks: int = setting(unit="ticks", low=1, high=10000, doc="ticks between checks (25 ms at 400 Hz)")
    monitor_margin: float = setting(low=1, high=100, doc="drop when error(model) > margin * error(nominal) + floor")
    monitor_floor: float = setting(unit="m/s^2", low=0, high=100,
        doc="estimator noise and command lag; a model is never dropped below this")
    latency: Literal["cpu", "fixed", "wall"] = setting(
        doc="lockstep flights' delay from a window's end to its model flying: cpu | fixed | wall")
    fixed_latency_s: float = setting(unit="s", low=0, high=60, doc="latency: fixed")
    latency_quantum_s: float = setting(unit="s", low=0, high=1, doc="latency: cpu")
    min_height: float = setting(unit="m", low=0, high=2,
        doc="ticks closer than this to the floor are not learned from (lower it to learn ground effect)")
    command_lag_s: tuple[float, float] = setting(unit="s", low=0, high=0.5,
        doc="(x/y, z) lags the commands act through (attitude loop, motors): learning targets use the lagged command")
    inject: FaultInjection


@dataclass(frozen=True)
class RadioConfig:
    uri: str = setting(doc="radio://0/80/2M/E7E7E7E7E7 on hardware")
    tx_rate_hz: float = setting(unit="Hz", low=20, high=500,
        doc="setpoints per second over the radio (100-200: docs/hardware.md#radio-budget)")
    imu_log: bool = setting(True, doc="log acc.x/y/z at 100 Hz for the loop (docs/hardware.md#imu-log)")
    stale_hold_slots: int = setting(4, unit="slots", low=1, high=50,
        doc="TX slots resending one setpoint before the radio flies a level, descending hold")
    stale_stop_s: float = setting(1.0, unit="s", low=0.1, high=2, open_high=True,
        doc="a held setpoint this old stops the motors and the e-stop heartbeat")


@dataclass(frozen=True)
class LogConfig:
    dir: str = setting(doc="one MCAP file per flight is written here")


@dataclass(frozen=True)
class DashboardConfig:
    enabled: bool = setting(doc="false (or `cfknode fly --headless`) flies without it")
    refresh_hz: float = setting(unit="Hz", low=0.5, high=30,
        doc="frames per second; spaced out further if a frame ever costs > 2% of wall time")


@dataclass(frozen=True)
class HardwareConfig:
    robot: str = setting(doc="robot name in the robots file = mocap rigid-body name (Crazyswarm2)")
    robots_file: str = setting(
        doc="Crazyswarm2-style robots YAML; \"\" = the packaged example (cfknode/config/robots.yaml)")
    mocap_type: Literal["vicon", "optitrack", "qualisys", "vrpn", "mock"] = setting(
        doc="vicon | optitrack | qualisys | vrpn | mock (libmotioncapture types: docs/hardware.md#mocap)")
    mocap_host: str = setting(doc="mocap server hostname or IP (vicon: host[:801]); not needed for mock")
    mocap_connect_timeout: float = setting(unit="s", low=0, high=120, open_low=True,
        doc="libmotioncapture's connect loops forever when the host is silent")
    mocap_rate_hz: float = setting(unit="Hz", low=10, high=1000,
        doc="Hz expected; Crazyswarm2 warns outside 80-120 Hz (docs/hardware.md#mocap)")
    radio_connect_timeout: float = setting(unit="s", low=0, high=120, open_low=True,
        doc="s for link, TOCs and parameter values (TOC cache makes it ~1 s)")
    preflight_settle: float = setting(unit="s", low=0.2, high=30,
        doc="s of mocap and telemetry streaming before the pre-flight checks")
    preflight_position_tolerance: float = setting(unit="m", low=0.01, high=5,
        doc="m between the rigid body and the robot's initial_position")
    preflight_max_tilt_deg: float = setting(unit="deg", low=0, high=90, open_low=True, open_high=True,
        doc="a robot tilted more than this on the ground (or a mis-defined mocap object) is refused")
    force: bool = setting(doc="fly even when a pre-flight check fails (logged)")
    extpos_std: float = setting(unit="m", low=0, high=1, open_low=True,
        doc="locSrv.extPosStdDev (Crazyswarm2's 1e-3; firmware default 0.01; docs/hardware.md#extpose)")
    extquat_std: float = setting(low=0, high=1, open_low=True,
        doc="locSrv.extQuatStdDev (Crazyswarm2's 0.05; firmware default 4.5e-3)")
    heartbeat_hz: float = setting(unit="Hz", low=0, high=50,
        doc="emergency-stop-watchdog heartbeat (protocol >= 12); 0 = off (docs/hardware.md#emergency-stop)")
    reboot_after_heartbeat: bool = setting(
        doc="the armed watchdog locks the drone 1 s after the last heartbeat, so reboot it after landing")
    telemetry_hz: float = setting(unit="Hz", low=0.4, high=100,
        doc="pm.vbat, pm.state, supervisor.info, radio.rssi log block rate")
    rw_cache: str = setting(doc="cflib TOC cache directory; \"\" = <user cache>/cfknode/cflib")


@dataclass(frozen=True)
class Config:
    backend: Literal["sim", "cf"] = setting(doc="sim | cf")
    vehicle: VehicleConfig
    controller: ControllerConfig
    estimator: EstimatorConfig
    trajectory: TrajectoryConfig
    sim: SimConfig
    knode: KnodeConfig
    training: TrainingConfig
    online: OnlineConfig
    radio: RadioConfig
    log: LogConfig
    dashboard: DashboardConfig
    safety: SafetyConfig
    faults: FaultsConfig
    hardware: HardwareConfig
    fleet: FleetConfig

    def to_dict(self) -> dict[str, Any]:
        return _plain(dataclasses.asdict(self))


def _plain(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj
