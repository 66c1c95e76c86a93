"""Settings of the safety supervisor: fence, watchdogs, battery, landing."""

from __future__ import annotations

from dataclasses import dataclass

from cfknode.kernel.setting import setting
from cfknode.kernel.vehicle import Vec3


@dataclass(frozen=True)
class SafetyConfig:
    enabled: bool = setting(doc="false: watchdogs and fence off (operator controls stay); for comparison runs only")
    estop_dir: str = setting(
        doc="`cfknode estop` mailbox, private to the user; \"\" = $XDG_RUNTIME_DIR/cfknode, else the cache dir")
    fence_min: Vec3 = setting(unit="m", low=-50, high=50,
        doc="world: hard geofence box's low corner; crossing it lands")
    fence_max: Vec3 = setting(unit="m", low=-50, high=50,
        doc="world: hard geofence box's high corner; crossing it lands")
    fence_margin: float = setting(unit="m", low=0, high=1,
        doc="the reference is clamped this far inside the box (not at the floor)")
    fence_stop_distance: float = setting(unit="m", low=0, high=5, open_low=True,
        doc="m outside the box: stop the motors instead of landing")
    fence_brake_tilt_deg: float = setting(unit="deg", low=5, high=60,
        doc="tilt the landing after a fence crossing may use until back inside the soft box (docs/design.md#safety)")
    mocap_hold_s: float = setting(unit="s", low=0, high=1, open_low=True,
        doc="s without a mocap frame: level out and sink (50-100 ms: docs/hardware.md#host-safety)")
    mocap_stop_s: float = setting(unit="s", low=0, high=5, open_low=True, doc="s without a frame: stop the motors")
    hold_thrust_factor: float = setting(low=0.5, high=1, open_high=True,
        doc="thrust while blind, as a fraction of hover thrust (sinks at ~0.8 m/s^2)")
    link_silence_s: float = setting(unit="s", low=0.01, high=2, doc="s without an acknowledged packet: land")
    link_max_latency_s: float = setting(unit="s", low=0, high=1, open_low=True,
        doc="s radio round trip (cflib link statistics) above which the flight lands")
    overrun_ticks: int = setting(unit="ticks", low=1, high=10000,
        doc="missed deadlines in a row that land the flight (wall clock only)")
    solve_deadline_s: float = setting(unit="s", low=0, high=0.1, open_low=True,
        doc="an MPC solve slower than this is replaced by the fallback (wall clock only)")
    battery_takeoff_min_v: float = setting(unit="V", low=3.0, high=4.35,
        doc="V at rest: refuse take-off below (Crazyswarm2 critical 3.7; docs/hardware.md#battery)")
    battery_land_v: float = setting(unit="V", low=3.0, high=4.35,
        doc="V filtered, under load: land below (3.1-3.2, pm.lowVoltage: docs/hardware.md#battery)")
    battery_filter_s: float = setting(unit="s", low=0, high=5, open_low=True,
        doc="time constant of the voltage low-pass (load transients sag vbat)")
    max_tilt_deg: float = setting(unit="deg", low=20, high=90,
        doc="deg from level (mocap attitude): stop the motors (tumbled)")
    tumble_s: float = setting(unit="s", low=0, high=1,
        doc="s the tilt must persist (one bad mocap frame is not a tumble)")
    max_tracking_error: float = setting(unit="m", low=0.05, high=5,
        doc="between position and reference: land (horizontal only during take-off)")
    tracking_error_s: float = setting(unit="s", low=0, high=5, doc="s the error must persist")
    max_fallback_s: float = setting(unit="s", low=0, high=10, open_low=True,
        doc="s of MPC failures in a row (geometric fallback) that land the flight")
    land_speed: float = setting(unit="m/s", low=0.05, high=2, doc="peak descent speed of a supervisor landing")
    touchdown_height: float = setting(unit="m", low=0, high=0.2, open_low=True,
        doc="m above the ground: a landing that reached it cuts the motors")
    preflight_timeout_s: float = setting(unit="s", low=0, high=60, open_low=True,
        doc="s to see the first mocap frame before take-off is refused")
    start_tolerance: float = setting(unit="m", low=0.01, high=5,
        doc="the start pose must be this close to the trajectory's start")
