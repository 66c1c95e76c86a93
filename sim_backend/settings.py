"""Settings of the simulator: the plant, its scenario events and the injected faults."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from cfknode.kernel.vehicle import Vec3


@dataclass(frozen=True)
class MassChange:
    t: float
    factor: float


@dataclass(frozen=True)
class DownwashConfig:
    """Downwash between simulated drones (fleet flights; sim_backend/downwash.py, docs/fleet.md#downwash)."""

    enabled: bool = False
    peak_fraction: float = 0.15  # downward force on a drone right below, as a fraction of the upper drone's thrust
    height: float = 1.0  # m of vertical gap at which the force has fallen to zero (linearly)
    radius: float = 0.1  # m, Gaussian radial scale of the wake (rotor-disk / airframe scale)


@dataclass(frozen=True)
class AeroTerms:
    """The realistic plant's terms (``sim.aero: realistic``); 0 turns one off. Sources: docs/hardware.md#simulator."""

    rotor_drag: float = 0.25  # m/s^2 per m/s of airspeed in the rotor plane, at hover rotor speed
    inflow: float = 0.4  # m/s^2 of thrust lost per m/s of airspeed along the rotor axis (a climb), at hover
    ground_effect: float = 1.0  # scale of the measured ground-effect lift (1: +10 % of the thrust at 3-5 cm)
    downwash: float = 1.0  # scale of the measured wake on a drone below another (1: 29 % of the thrust at 0.25 m)
    downwash_width: float = 0.058  # m, standard deviation of the wake's lateral Gaussian
    fast_rms: float = 0.15  # m/s^2 per axis, the fast random force's RMS at zero airspeed
    fast_rms_per_speed2: float = 0.08  # m/s^2 per (m/s)^2 of airspeed, added to fast_rms
    # Hz, the fast force's band: a first-order high-pass, a second-order low-pass.
    fast_band_hz: tuple[float, float] = (1.0, 10.0)


@dataclass(frozen=True)
class SimConfig:
    seed: int
    dt: float
    realtime: bool
    initial_position: Vec3
    battery_voltage: float
    mocap_rate_hz: float
    mocap_position_noise: float
    mocap_attitude_noise: float
    mocap_latency: float
    mocap_dropout_prob: float
    mass_changes: tuple[MassChange, ...]
    wind: Vec3
    drag: Vec3
    # Plants the controller was not tuned on (it keeps believing ``vehicle:``); the defaults
    # reproduce the vehicle config exactly. Ranges and sources: cfknode/config/default.yaml.
    motor_time_constant: float | None = None  # s, the plant's motor lag; None = vehicle.motor_time_constant
    thrust_map_scale: float = 1.0  # true force per command / the vehicle config's
    battery_sag_per_s: float = 0.0  # fraction of thrust_map_scale lost per second of sim time
    attitude_gain: float = 1.0  # roll/pitch the attitude loop tracks / the commanded angle
    yaw_gain: float = 1.0  # yaw rate the attitude loop tracks / the commanded rate
    downwash: DownwashConfig = DownwashConfig()
    # m/s^2, std per accelerometer sample (acc.x/y/z), each axis. An assumption for a vibrating Crazyflie 2.x
    # after the firmware's low-pass filtering: docs/hardware.md#imu-log.
    imu_noise: float = 0.3
    # ideal: rigid body, lagged motors, sim.drag and wind; realistic: plus aero_terms (sim_backend/aero_vehicle.py).
    aero: Literal["ideal", "realistic"] = "ideal"
    aero_terms: AeroTerms = AeroTerms()


@dataclass(frozen=True)
class FaultWindow:
    t: float
    duration: float


@dataclass(frozen=True)
class Gust:
    t: float
    duration: float
    wind: Vec3


@dataclass(frozen=True)
class FaultsConfig:
    mocap_outages: tuple[FaultWindow, ...]
    radio_outages: tuple[FaultWindow, ...]
    solver_failures: tuple[FaultWindow, ...]
    nan_model_at: float
    battery_drop_at: float
    battery_drop_to: float
    gusts: tuple[Gust, ...]
    sigint_at: tuple[float, ...]
