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
from cfknode.kernel.vehicle import VehicleConfig
from cfknode.models.settings import FaultInjection, KnodeConfig, TrainingConfig
from cfknode.safety.settings import SafetyConfig
from cfknode.sim_backend.settings import FaultsConfig, SimConfig

__all__ = ["Config", "DashboardConfig", "HardwareConfig", "LogConfig", "OnlineConfig", "RadioConfig"]

@dataclass(frozen=True)
class OnlineConfig:
    enabled: bool
    t_col: float
    epochs: int
    method: Literal["rk4", "euler", "dopri5"]
    lr: float
    weight_decay: float
    warm_start: bool
    replay_windows: int
    paper_lockstep: bool
    gate: bool
    gate_min_pairs: int
    gate_control_gain: tuple[float, float]
    gate_max_velocity_gain: float
    gate_max_cross_gain: float
    gate_max_tilt_climb: float
    gate_layer_margin: float
    gate_layer_steps: int
    gate_layer_min_gain: float
    trainer_timeout: float
    max_restarts: int
    start_time: float
    rollback_ticks: int
    rollback_fallbacks: int
    monitor: bool
    monitor_window_s: float
    monitor_every_ticks: int
    monitor_margin: float
    monitor_floor: float
    latency: Literal["cpu", "fixed", "wall"]
    fixed_latency_s: float
    latency_quantum_s: float
    inject: FaultInjection


@dataclass(frozen=True)
class RadioConfig:
    uri: str
    tx_rate_hz: float
    imu_log: bool = True  # the accelerometer log block (docs/hardware.md#imu-log)
    stale_hold_slots: int = 4  # TX slots resending one setpoint before the radio holds level, descending
    stale_stop_s: float = 1.0  # s: a setpoint this old (and held) makes the radio stop the motors


@dataclass(frozen=True)
class LogConfig:
    dir: str


@dataclass(frozen=True)
class DashboardConfig:
    enabled: bool
    refresh_hz: float


@dataclass(frozen=True)
class HardwareConfig:
    robot: str
    robots_file: str
    mocap_type: Literal["vicon", "optitrack", "qualisys", "vrpn", "mock"]
    mocap_host: str
    mocap_connect_timeout: float
    mocap_rate_hz: float
    radio_connect_timeout: float
    preflight_settle: float
    preflight_position_tolerance: float
    preflight_max_tilt_deg: float
    force: bool
    extpos_std: float
    extquat_std: float
    heartbeat_hz: float
    reboot_after_heartbeat: bool
    telemetry_hz: float
    rw_cache: str


@dataclass(frozen=True)
class Config:
    backend: Literal["sim", "cf"]
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
