"""Settings of the flight package: the controller, the velocity estimator, the reference trajectory."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from cfknode.kernel.vehicle import Vec3


@dataclass(frozen=True)
class AdaptationTuning:
    """Gains and bounds of the fast adaptation layer (``cfknode.flight.adaptation.AdaptationSettings``)."""

    bandwidth_hz: float
    bandwidth_xy_hz: float
    predictor_gain: float
    adaptation_gain: float
    thrust_rate: float
    axis_rate: float
    max_offset: float
    thrust_scale_bounds: tuple[float, float]
    axis_gain_bounds: tuple[float, float]
    stale_pose_s: float
    rebase_window_s: float


@dataclass(frozen=True)
class ControllerConfig:
    kind: Literal["mpc", "knode-mpc", "geometric"]
    model: str
    rate_hz: float
    horizon: int
    dt: float
    solver: Literal["rti", "ipopt"]
    qp_solver: Literal["qrqp", "osqp"]
    codegen: bool
    q_position: Vec3
    q_velocity: Vec3
    r_acceleration: Vec3
    terminal_scale: float
    max_tilt_deg: float
    min_thrust_fraction: float
    max_thrust_fraction: float
    yaw_rate_gain: float
    max_yaw_rate_deg: float
    geometric_kp: Vec3
    geometric_kd: Vec3
    adaptation: Literal["none", "l1", "dob", "oracle"]
    adaptation_settings: AdaptationTuning


@dataclass(frozen=True)
class EstimatorConfig:
    process_accel_std: float
    position_std: float
    latency: float
    command_delay: float = 0.0  # s from a sent command to its acceleration; the plan starts that far ahead


@dataclass(frozen=True)
class TrajectoryConfig:
    kind: Literal["hover", "circle", "figure8"]
    radius: float
    speed: float
    center: tuple[float, float]
    height: float
    duration: float
    takeoff_duration: float
    settle_duration: float
    land_duration: float
    ramp_duration: float
