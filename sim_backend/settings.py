"""Settings of the simulator: the plant, its scenario events and the injected faults."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from cfknode.kernel.setting import setting
from cfknode.kernel.vehicle import Vec3


@dataclass(frozen=True)
class MassChange:
    t: float = setting(unit="s", low=0, high=3600, doc="flight time of the mass change")
    factor: float = setting(unit="x nominal mass", low=0.25, high=4.0, doc="new mass / nominal mass")


@dataclass(frozen=True)
class DownwashConfig:
    """Downwash between simulated drones (fleet flights; sim_backend/downwash.py, docs/fleet.md#downwash)."""

    enabled: bool = setting(False, doc="push a drone below another down (fleet flights, ideal plant)")
    peak_fraction: float = setting(0.15, low=0, high=1,
        doc="downward force right below, as a fraction of the upper drone's thrust")
    height: float = setting(1.0, unit="m", low=0, high=5, open_low=True,
        doc="vertical gap at which the force has fallen (linearly) to zero")
    radius: float = setting(0.1, unit="m", low=0, high=1, open_low=True, doc="Gaussian radial scale of the wake")


@dataclass(frozen=True)
class AeroTerms:
    """The realistic plant's terms (``sim.aero: realistic``); 0 turns one off. Sources: docs/hardware.md#simulator."""

    rotor_drag: float = setting(0.25, unit="m/s^2 per m/s", low=0, high=2,
        doc="drag per airspeed in the rotor plane, at hover rotor speed")
    inflow: float = setting(0.4, unit="m/s^2 per m/s", low=0, high=2,
        doc="thrust lost per airspeed along the rotor axis (a climb), at hover")
    ground_effect: float = setting(1.0, low=0, high=3,
        doc="scale of the measured ground effect (1: +10 % of the thrust at 3-5 cm, 0 above 0.15 m)")
    downwash: float = setting(1.0, low=0, high=3,
        doc="scale of the measured wake on a drone below another (1: 29 % of the thrust at 0.25 m)")
    downwash_width: float = setting(0.058, unit="m", low=0.01, high=0.5,
        doc="standard deviation of the wake's lateral Gaussian")
    fast_rms: float = setting(0.15, unit="m/s^2", low=0, high=2,
        doc="per axis, RMS of the fast random force at zero airspeed")
    fast_rms_per_speed2: float = setting(0.08, unit="m/s^2 per (m/s)^2", low=0, high=1,
        doc="per squared airspeed, added to fast_rms")
    fast_band_hz: tuple[float, float] = setting((1.0, 10.0), unit="Hz", low=0.05, high=100,
        doc="the fast force's band: a first-order high-pass, a second-order low-pass")


@dataclass(frozen=True)
class SimConfig:
    seed: int = setting(low=0, high=4294967295, doc="seed of the simulator's noise")
    dt: float = setting(unit="s", low=0.0001, high=0.01, doc="plant step (the paper: 2 ms)")
    realtime: bool = setting(doc="false: lockstep (as fast as it computes); true: wall clock")
    initial_position: Vec3 = setting(unit="m", low=-50, high=50, doc="start on the ground")
    battery_voltage: float = setting(unit="V", low=3.0, high=4.35,
        doc="V at start, discharged by a linear model under load")
    mocap_rate_hz: float = setting(unit="Hz", low=10, high=1000,
        doc="Crazyswarm2 expects 80-120 Hz (docs/hardware.md#mocap)")
    mocap_position_noise: float = setting(unit="m", low=0, high=0.1, doc="std; Vicon sub-mm")
    mocap_attitude_noise: float = setting(unit="rad", low=0, high=0.5, doc="std, small-angle rotation noise")
    mocap_latency: float = setting(unit="s", low=0, high=0.5, doc="a few ms for Vicon (docs/hardware.md#mocap)")
    mocap_dropout_prob: float = setting(low=0, high=1, open_high=True, doc="probability that a frame is lost")
    mass_changes: tuple[MassChange, ...] = setting(doc="list of {t: s, factor: new mass / nominal mass}")
    wind: Vec3 = setting(unit="m/s", low=-20, high=20, doc="constant air velocity (acts through drag)")
    drag: Vec3 = setting(unit="N/(m/s)", low=0, high=1, doc="linear drag coefficients on air-relative velocity")
    motor_time_constant: float | None = setting(None, unit="s", low=0, high=0.3,
        doc="the plant's motor thrust lag; null = vehicle.motor_time_constant")
    thrust_map_scale: float = setting(1.0, low=0.5, high=1.5, doc="true force per command / the vehicle config's")
    battery_sag_per_s: float = setting(0.0, unit="1/s", low=0, high=0.05,
        doc="fraction of thrust_map_scale lost per second (voltage compensation falling behind)")
    attitude_gain: float = setting(1.0, low=0.5, high=1.5,
        doc="roll/pitch the attitude loop tracks / the commanded angle")
    yaw_gain: float = setting(1.0, low=0.25, high=3, doc="yaw rate the attitude loop tracks / the commanded rate")
    downwash: DownwashConfig = DownwashConfig()
    imu_noise: float = setting(0.3, unit="m/s^2", low=0, high=5,
        doc="std per accelerometer sample and axis (acc.x/y/z) (docs/hardware.md#imu-log)")
    imu_bias: Vec3 = setting((0.0, 0.0, 0.0), unit="m/s^2", low=-2, high=2,
        doc="constant offset of acc.x/y/z, body frame; a BMI088's zero-g offset is up to 0.2 (docs/hardware.md#imu-log)")
    aero: Literal["ideal", "realistic"] = setting("realistic",
        doc="ideal: rigid body, lagged motors, drag and wind above | realistic: plus aero_terms")
    aero_terms: AeroTerms = AeroTerms()
    air_model: bool = setting(False,
        doc="fly the MPC with the plant's own air terms as its model: a bench's ceiling for learning (realistic plant)")
    air_model_from_s: float = setting(0.0, unit="s", low=0, high=3600,
        doc="flight time the air model starts flying (0: from take-off): what a model arriving then can at best do")
    air_model_terms: Literal["all", "wake"] = setting("all",
        doc="all: every air term | wake: the drone above's wake alone, a wake model's ceiling (fleet.neighbour_input)")


@dataclass(frozen=True)
class FaultWindow:
    t: float = setting(unit="s", low=0, high=3600, doc="flight time the window starts")
    duration: float = setting(unit="s", low=0, high=3600, doc="length of the window")


@dataclass(frozen=True)
class Gust:
    t: float = setting(unit="s", low=0, high=3600, doc="flight time the gust starts")
    duration: float = setting(unit="s", low=0, high=3600, doc="length of the gust")
    wind: Vec3 = setting(unit="m/s", low=-20, high=20, doc="air velocity during the gust")


@dataclass(frozen=True)
class FaultsConfig:
    mocap_outages: tuple[FaultWindow, ...] = setting(
        doc="list of {t: s, duration: s}: no mocap frames are sampled in [t, t + duration)")
    radio_outages: tuple[FaultWindow, ...] = setting(
        doc="list of {t, duration}: packets to the drone are lost (100 in a row drop the link for good)")
    solver_failures: tuple[FaultWindow, ...] = setting(doc="list of {t, duration}: the MPC reports a failed solve")
    nan_model_at: float = setting(unit="s", low=-math.inf, high=3600,
        doc="swap in a KNODE model whose residual is NaN (< 0: never)")
    battery_drop_at: float = setting(unit="s", low=-math.inf, high=3600,
        doc="the cell's open-circuit voltage drops to battery_drop_to (< 0: never)")
    battery_drop_to: float = setting(unit="V", low=3.0, high=4.35, doc="open circuit")
    gusts: tuple[Gust, ...] = setting(
        doc="list of {t, duration, wind: [x, y, z] m/s}: wind during the gust (acts through sim.drag)")
    sigint_at: tuple[float, ...] = setting(unit="s", low=0, high=3600,
        doc="the flight sends itself SIGINT (Ctrl-C) at these flight times")
