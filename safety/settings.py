"""Settings of the safety supervisor: fence, watchdogs, battery, landing."""

from __future__ import annotations

from dataclasses import dataclass

from cfknode.kernel.vehicle import Vec3


@dataclass(frozen=True)
class SafetyConfig:
    enabled: bool
    estop_dir: str
    fence_min: Vec3
    fence_max: Vec3
    fence_margin: float
    fence_stop_distance: float
    mocap_hold_s: float
    mocap_stop_s: float
    hold_thrust_factor: float
    link_silence_s: float
    link_max_latency_s: float
    overrun_ticks: int
    solve_deadline_s: float
    battery_takeoff_min_v: float
    battery_land_v: float
    battery_filter_s: float
    max_tilt_deg: float
    tumble_s: float
    max_tracking_error: float
    tracking_error_s: float
    max_fallback_s: float
    land_speed: float
    touchdown_height: float
    preflight_timeout_s: float
    start_tolerance: float
