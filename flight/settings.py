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
    thrust_lag_s: float | None = None  # s, the motors' thrust lag the observer models; None: chosen in flight
    thrust_lag_candidates_s: tuple[float, ...] = (0.015, 0.04, 0.08, 0.15)  # s, with the vehicle's, when None
    step_threshold: float = 0.0  # vertical step detector's alarm level (noise-normalised CUSUM); 0 = off
    step_bandwidth_hz: float = 10.0  # vertical bandwidth for ``step_hold_s`` after an alarm
    step_thrust_rate: float = 400.0  # 1/s, thrust_rate for ``step_hold_s`` after an alarm
    step_hold_s: float = 0.3  # s the fast estimate lasts after an alarm
    step_max_s: float = 1.0  # s a step is tracked at most after its first alarm
    oracle_delay_s: float = 0.0  # s, adaptation "oracle" only: the true mass is told this late
    output_bandwidth_hz: float = 0.0  # dob: the vertical offset is the estimate low-passed again at this cut-off; 0 off
    output_bandwidth_xy_hz: float = 0.0  # the same for x and y
    offset_deadband: float = 0.0  # m/s^2: a horizontal offset well below it is shrunk toward 0; 0 off
    engage_level: float = 0.0  # m/s^2: an axis's estimate acts once it is above this; 0 = always acts
    engage_slow_level: float = float("inf")  # m/s^2: ... or once its slow mean is above this
    engage_slow_s: float = 2.0  # s, time constant of that mean
    release_s: float = 1.0  # s with both under half their levels before an axis lets go again


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
    cone_reserve_deg: float = 5.0  # deg the thrust cone leaves horizontal tracking at the clamp (fast adaptation only)


@dataclass(frozen=True)
class EstimatorConfig:
    process_accel_std: float
    position_std: float
    latency: float
    command_delay: float = 0.0  # s from a sent command to its acceleration; the plan starts that far ahead
    attitude_lag: float = 0.0  # s, time constant from a commanded horizontal acceleration to the one flown; 0: at once


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
