"""Physical bounds on every numeric config key, and checks that relate keys to each other.

A value that parses but makes the controller or the safety layer unsafe (a 1 Hz loop, negative
gravity, a zero time constant, a landing voltage above the take-off voltage) is refused when
the configuration loads, with one line naming the key, the bound and the unit.

``BOUNDS`` maps a dotted key to its range. A key whose value is a list (``vehicle.inertia``)
bounds every element; a key through a list of records (``sim.mass_changes.factor``) bounds that
field of every record. ``CROSS_CHECKS`` are small pure functions of the whole config that
return a one-line problem or ``None``. The ranges are for a Crazyflie 2.x class quadrotor
(about 30 g, 1S LiPo) flown indoors on Earth; see docs/ for the sources of the defaults.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Iterator

from cfknode.app.settings import Config
from cfknode.kernel.errors import ConfigError

INF = math.inf


@dataclass(frozen=True)
class Bound:
    """``low`` .. ``high`` in ``unit``; an open end excludes the end itself."""

    low: float
    high: float
    unit: str = ""
    low_open: bool = False
    high_open: bool = False

    def contains(self, value: float) -> bool:
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def describe(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        if self.high == INF:
            return f"{'above' if self.low_open else 'at least'} {self.low:g}{unit}"
        if self.low == -INF:
            return f"{'below' if self.high_open else 'at most'} {self.high:g}{unit}"
        if not self.low_open and not self.high_open:
            return f"{self.low:g} to {self.high:g}{unit}"
        low = f"above {self.low:g}" if self.low_open else f"at least {self.low:g}"
        high = f"below {self.high:g}" if self.high_open else f"at most {self.high:g}"
        return f"{low} and {high}{unit}"


def _b(low: float, high: float, unit: str = "", *, open_low: bool = False, open_high: bool = False) -> Bound:
    return Bound(low, high, unit, open_low, open_high)


_SEED = _b(0, 2**32 - 1)  # numpy's seed range
_LIPO = _b(3.0, 4.35, "V")  # one LiPo cell: empty under load .. fully charged (high-voltage cells)
_SIM_TIME = _b(0, 3600, "s")  # a simulated flight is never longer than an hour
_WIND = _b(-20, 20, "m/s")  # indoor flight; a 30 g quadrotor cannot hold against more
_ROUND = _b(0, 100_000)

BOUNDS: dict[str, Bound] = {
    # Vehicle: a Crazyflie 2.x with decks and markers (29 g stock, ~40 g loaded or brushless).
    "vehicle.mass": _b(0.015, 0.1, "kg"),
    "vehicle.inertia": _b(5e-6, 5e-4, "kg m^2"),  # diagonal; stock 1.7e-5 .. 2.9e-5
    "vehicle.arm_length": _b(0.02, 0.1, "m"),
    "vehicle.thrust_max_per_motor": _b(0.05, 0.5, "N"),  # stock 0.12, thrust-upgrade / brushless more
    "vehicle.thrust_cmd_clamp": _b(20_000, 65_535),  # 16-bit thrust command
    "vehicle.thrust_to_torque": _b(0.001, 0.05, "m"),
    "vehicle.motor_time_constant": _b(0.005, 0.2, "s"),  # a real motor always lags; 0 hid that
    "vehicle.gravity": _b(9.0, 10.5, "m/s^2"),  # Earth (9.78 .. 9.83) with room for rounding
    # Controller.
    "controller.rate_hz": _b(50, 1000, "Hz"),  # slower cannot stabilise the translational loop
    "controller.horizon": _b(2, 200, "nodes"),
    "controller.dt": _b(0, 0.5, "s", open_low=True),
    "controller.q_position": _b(0, 1e6),
    "controller.q_velocity": _b(0, 1e6),
    "controller.r_acceleration": _b(0, 1e6, open_low=True),  # > 0 keeps the QP strictly convex in u
    "controller.terminal_scale": _b(0, 1000),
    "controller.max_tilt_deg": _b(5, 60, "deg"),
    "controller.min_thrust_fraction": _b(0, 0.9),
    "controller.max_thrust_fraction": _b(0.5, 1.0),
    "controller.cone_reserve_deg": _b(0, 20, "deg"),
    "controller.yaw_rate_gain": _b(0, 20, "1/s"),
    "controller.max_yaw_rate_deg": _b(0, 360, "deg/s", open_low=True),
    "controller.geometric_kp": _b(0, 10, "N/m", open_low=True),
    "controller.geometric_kd": _b(0, 5, "N/(m/s)"),
    # Fast adaptation: observer bandwidths well below the 400 Hz tick, estimates physically plausible.
    "controller.adaptation_settings.bandwidth_hz": _b(0, 50, "Hz", open_low=True),
    "controller.adaptation_settings.bandwidth_xy_hz": _b(0, 50, "Hz", open_low=True),
    "controller.adaptation_settings.predictor_gain": _b(0, 1000, "1/s", open_low=True),
    "controller.adaptation_settings.adaptation_gain": _b(0, 1e5),
    "controller.adaptation_settings.thrust_rate": _b(0, 200, "1/s"),
    "controller.adaptation_settings.axis_rate": _b(0, 200, "1/s"),
    "controller.adaptation_settings.max_offset": _b(0, 20, "m/s^2"),
    "controller.adaptation_settings.thrust_scale_bounds": _b(0.1, 10, "x nominal mass", open_low=True),
    "controller.adaptation_settings.axis_gain_bounds": _b(0.1, 10, open_low=True),
    "controller.adaptation_settings.stale_pose_s": _b(0, 1, "s", open_low=True),
    "controller.adaptation_settings.rebase_window_s": _b(0, 5, "s", open_low=True),
    "controller.adaptation_settings.step_threshold": _b(0, 1000),
    "controller.adaptation_settings.step_bandwidth_hz": _b(0, 50, "Hz", open_low=True),
    "controller.adaptation_settings.step_thrust_rate": _b(0, 1000, "1/s"),
    "controller.adaptation_settings.step_hold_s": _b(0, 5, "s"),
    "controller.adaptation_settings.step_max_s": _b(0, 10, "s", open_low=True),
    "controller.adaptation_settings.oracle_delay_s": _b(0, 1, "s"),
    "controller.adaptation_settings.output_bandwidth_hz": _b(0, 50, "Hz"),
    "controller.adaptation_settings.output_bandwidth_xy_hz": _b(0, 50, "Hz"),
    "controller.adaptation_settings.offset_deadband": _b(0, 5, "m/s^2"),
    "controller.adaptation_settings.engage_level": _b(0, 2, "m/s^2"),
    "controller.adaptation_settings.engage_slow_level": _b(0, 2, "m/s^2", open_low=True),
    "controller.adaptation_settings.engage_slow_s": _b(0, 60, "s", open_low=True),
    "controller.adaptation_settings.release_s": _b(0, 60, "s"),
    "controller.adaptation_settings.thrust_lag_candidates_s": _b(0.001, 0.5, "s"),
    # Estimator.
    "estimator.process_accel_std": _b(0, 100, "m/s^2", open_low=True),
    "estimator.position_std": _b(1e-5, 0.1, "m"),  # the Kalman filter needs a noise > 0
    "estimator.latency": _b(0, 0.2, "s"),
    # Trajectory (whether it fits the fence and the limits is checked before take-off).
    "trajectory.radius": _b(0.05, 5, "m"),
    "trajectory.speed": _b(0.01, 5, "m/s"),
    "trajectory.center": _b(-50, 50, "m"),
    "trajectory.height": _b(0.1, 5, "m"),
    "trajectory.duration": _b(0, 3600, "s"),
    "trajectory.takeoff_duration": _b(0.5, 60, "s"),
    "trajectory.settle_duration": _b(0, 60, "s"),
    "trajectory.land_duration": _b(0.5, 60, "s"),
    "trajectory.ramp_duration": _b(0, 60, "s"),
    # Simulator.
    "sim.seed": _SEED,
    "sim.dt": _b(1e-4, 0.01, "s"),
    "sim.initial_position": _b(-50, 50, "m"),
    "sim.battery_voltage": _LIPO,
    "sim.mocap_rate_hz": _b(10, 1000, "Hz"),
    "sim.mocap_position_noise": _b(0, 0.1, "m"),
    "sim.mocap_attitude_noise": _b(0, 0.5, "rad"),
    "sim.mocap_latency": _b(0, 0.5, "s"),
    "sim.mocap_dropout_prob": _b(0, 1, open_high=True),
    "sim.imu_noise": _b(0, 5, "m/s^2"),  # 5 m/s^2 is half a g of noise on every sample: a broken mount
    "sim.mass_changes.t": _SIM_TIME,
    "sim.mass_changes.factor": _b(0.25, 4.0, "x nominal mass"),  # the range the online gate is built for
    "sim.wind": _WIND,
    "sim.drag": _b(0, 1, "N/(m/s)"),  # drag only takes energy out
    "sim.thrust_map_scale": _b(0.5, 1.5),  # identified maps of individual Crazyflies differ by about 15 %
    "sim.battery_sag_per_s": _b(0, 0.05, "1/s"),
    "sim.attitude_gain": _b(0.5, 1.5),
    "sim.yaw_gain": _b(0.25, 3),
    "sim.downwash.peak_fraction": _b(0, 1),
    "sim.downwash.height": _b(0, 5, "m", open_low=True),
    "sim.downwash.radius": _b(0, 1, "m", open_low=True),
    # The realistic plant's terms (0: off; 1x the documented values is the default, docs/hardware.md#simulator).
    "sim.aero_terms.rotor_drag": _b(0, 2, "m/s^2 per m/s"),
    "sim.aero_terms.inflow": _b(0, 2, "m/s^2 per m/s"),
    "sim.aero_terms.ground_effect": _b(0, 3),
    "sim.aero_terms.downwash": _b(0, 3),
    "sim.aero_terms.downwash_width": _b(0.01, 0.5, "m"),
    "sim.aero_terms.fast_rms": _b(0, 2, "m/s^2"),
    "sim.aero_terms.fast_rms_per_speed2": _b(0, 1, "m/s^2 per (m/s)^2"),
    "sim.aero_terms.fast_band_hz": _b(0.05, 100, "Hz"),
    "estimator.command_delay": _b(0, 0.3, "s"),
    "estimator.attitude_lag": _b(0, 1, "s"),
    "fleet.size": _b(0, 16, "drones"),
    "fleet.min_separation": _b(0, 5, "m"),
    "fleet.hold_s": _b(0, 10, "s"),
    "fleet.stack_spacing": _b(0, 5, "m"),
    "fleet.ground_spacing": _b(0, 5, "m"),
    "fleet.drones_per_sim_radio": _b(1, 16, "drones"),
    "fleet.radio_budget_pps": _b(50, 2000, "packets/s"),
    "fleet.ping_hz": _b(0, 100, "Hz"),
    # KNODE networks and training.
    "knode.hidden": _b(1, 1024, "units"),
    "knode.queue_size": _b(1, 10),
    "knode.max_residual": _b(0, 100, "m/s^2", open_low=True),
    "training.epochs": _b(1, 100_000),
    "training.batch_size": _b(64, 10_000_000),
    "training.lr": _b(0, 1, open_low=True),
    "training.weight_decay": _b(0, 100),
    "training.seed": _SEED,
    "training.velocity_filter_hz": _b(0.5, 100, "Hz"),
    "training.validation_fraction": _b(0, 1, open_low=True, open_high=True),
    # Online learning.
    "online.t_col": _b(0.05, 60, "s"),
    "online.epochs": _b(1, 10_000),
    "online.lr": _b(0, 1, open_low=True),
    "online.weight_decay": _b(0, 100),
    "online.replay_windows": _b(0, 20),
    "online.gate_min_pairs": _b(2, 100_000),
    "online.gate_control_gain": _b(0, 100, open_low=True),
    "online.gate_max_velocity_gain": _b(0, 100, "1/s"),
    "online.gate_max_cross_gain": _b(0, 10),
    "online.gate_max_tilt_climb": _b(0, 10, "m/s^2"),
    "online.gate_layer_margin": _b(0, 1),
    "online.gate_layer_steps": _b(1, 400, "pairs"),
    "online.gate_layer_min_gain": _b(0, 10, "m/s^2"),
    "online.trainer_timeout": _b(0, 600, "s", open_low=True),
    "online.max_restarts": _b(0, 100),
    "online.start_time": _SIM_TIME,
    "online.rollback_ticks": _b(1, 100_000, "ticks"),
    "online.rollback_fallbacks": _b(1, 100_000),
    "online.monitor_window_s": _b(0, 2, "s", open_low=True),
    "online.monitor_every_ticks": _b(1, 10_000, "ticks"),
    "online.monitor_margin": _b(1, 100),
    "online.monitor_floor": _b(0, 100, "m/s^2"),
    "online.fixed_latency_s": _b(0, 60, "s"),
    "online.latency_quantum_s": _b(0, 1, "s"),
    "online.inject.crash_at_round": _ROUND,
    "online.inject.hang_at_round": _ROUND,
    "online.inject.nan_at_round": _ROUND,
    # Radio and display.
    "radio.tx_rate_hz": _b(20, 500, "Hz"),  # slower and the firmware's setpoint watchdog trips
    "radio.stale_hold_slots": _b(1, 50, "slots"),
    "radio.stale_stop_s": _b(0.1, 2, "s", open_high=True),  # the firmware's commander watchdog locks at 2 s
    "dashboard.refresh_hz": _b(0.5, 30, "Hz"),
    # Safety supervisor.
    "safety.fence_min": _b(-50, 50, "m"),
    "safety.fence_max": _b(-50, 50, "m"),
    "safety.fence_margin": _b(0, 1, "m"),
    "safety.fence_stop_distance": _b(0, 5, "m", open_low=True),
    "safety.mocap_hold_s": _b(0, 1, "s", open_low=True),
    "safety.mocap_stop_s": _b(0, 5, "s", open_low=True),
    "safety.hold_thrust_factor": _b(0.5, 1, open_high=True),
    "safety.link_silence_s": _b(0.01, 2, "s"),
    "safety.link_max_latency_s": _b(0, 1, "s", open_low=True),
    "safety.overrun_ticks": _b(1, 10_000, "ticks"),
    "safety.solve_deadline_s": _b(0, 0.1, "s", open_low=True),
    "safety.battery_takeoff_min_v": _LIPO,
    "safety.battery_land_v": _LIPO,
    "safety.battery_filter_s": _b(0, 5, "s", open_low=True),
    "safety.max_tilt_deg": _b(20, 90, "deg"),
    "safety.tumble_s": _b(0, 1, "s"),
    "safety.max_tracking_error": _b(0.05, 5, "m"),
    "safety.tracking_error_s": _b(0, 5, "s"),
    "safety.max_fallback_s": _b(0, 10, "s", open_low=True),
    "safety.land_speed": _b(0.05, 2, "m/s"),
    "safety.touchdown_height": _b(0, 0.2, "m", open_low=True),
    "safety.preflight_timeout_s": _b(0, 60, "s", open_low=True),
    "safety.start_tolerance": _b(0.01, 5, "m"),
    # Fault injection (simulation only; the windows' own rules are in sim_backend/faults.py).
    "faults.mocap_outages.t": _SIM_TIME,
    "faults.mocap_outages.duration": _SIM_TIME,
    "faults.radio_outages.t": _SIM_TIME,
    "faults.radio_outages.duration": _SIM_TIME,
    "faults.solver_failures.t": _SIM_TIME,
    "faults.solver_failures.duration": _SIM_TIME,
    "faults.nan_model_at": _b(-INF, 3600, "s"),  # < 0: never
    "faults.battery_drop_at": _b(-INF, 3600, "s"),  # < 0: never
    "faults.battery_drop_to": _LIPO,
    "faults.gusts.t": _SIM_TIME,
    "faults.gusts.duration": _SIM_TIME,
    "faults.gusts.wind": _WIND,
    "faults.sigint_at": _SIM_TIME,
    # Hardware backend.
    "hardware.mocap_connect_timeout": _b(0, 120, "s", open_low=True),
    "hardware.mocap_rate_hz": _b(10, 1000, "Hz"),
    "hardware.radio_connect_timeout": _b(0, 120, "s", open_low=True),
    "hardware.preflight_settle": _b(0.2, 30, "s"),
    "hardware.preflight_position_tolerance": _b(0.01, 5, "m"),
    "hardware.preflight_max_tilt_deg": _b(0, 90, "deg", open_low=True, open_high=True),
    "hardware.extpos_std": _b(0, 1, "m", open_low=True),
    "hardware.extquat_std": _b(0, 1, open_low=True),
    "hardware.heartbeat_hz": _b(0, 50, "Hz"),
    "hardware.telemetry_hz": _b(0.4, 100, "Hz"),
}


def leaves(cfg: Any, dotted: str) -> Iterator[tuple[str, Any]]:
    """(label, value) for every number a bounds key addresses: list elements and record fields."""
    found: list[tuple[str, Any]] = [("", cfg)]
    parts = dotted.split(".")
    for n, part in enumerate(parts):
        nxt: list[tuple[str, Any]] = []
        for label, obj in found:
            value = getattr(obj, part)
            label = f"{label}.{part}" if label else part
            if isinstance(value, tuple) and n < len(parts) - 1:  # a list of records: each one's field
                nxt.extend((f"{label}[{i}]", v) for i, v in enumerate(value))
            else:
                nxt.append((label, value))
        found = nxt
    for label, value in found:
        if isinstance(value, tuple):
            yield from ((f"{label}[{i}]", v) for i, v in enumerate(value))
        else:
            yield label, value


def _fmt(value: float) -> str:
    return str(value) if isinstance(value, int) else f"{value:g}"


def out_of_bounds(cfg: Config) -> str | None:
    """The first value outside its bound, as one line, or None."""
    for key, bound in BOUNDS.items():
        for label, value in leaves(cfg, key):
            if not bound.contains(value):
                return f"{label} = {_fmt(value)} is out of range: must be {bound.describe()}"
    return None


# --- checks across keys: each a pure function returning a one-line problem or None -----------


def hover_authority(cfg: Config) -> str | None:
    """The thrust the MPC may plan must lift the vehicle, or it falls however it is commanded."""
    v, f = cfg.vehicle, cfg.controller.max_thrust_fraction
    lift = f * v.thrust_cmd_clamp * 4.0 * v.thrust_max_per_motor / 65535.0
    weight = v.mass * v.gravity
    if lift <= weight:
        return (f"vehicle cannot hover: controller.max_thrust_fraction x thrust at vehicle.thrust_cmd_clamp = "
                f"{lift:.3g} N is not above its weight {weight:.3g} N (vehicle.mass x vehicle.gravity)")
    return None


def battery_order(cfg: Config) -> str | None:
    s = cfg.safety
    if s.battery_land_v >= s.battery_takeoff_min_v:
        return (f"safety.battery_land_v = {s.battery_land_v:g} V must be below "
                f"safety.battery_takeoff_min_v = {s.battery_takeoff_min_v:g} V")
    return None


def radio_rate(cfg: Config) -> str | None:
    """More setpoints than control ticks would resend stale ones."""
    if cfg.radio.tx_rate_hz > cfg.controller.rate_hz:
        return (f"radio.tx_rate_hz = {cfg.radio.tx_rate_hz:g} Hz must be at most "
                f"controller.rate_hz = {cfg.controller.rate_hz:g} Hz")
    return None


def stale_order(cfg: Config) -> str | None:
    """The radio's hold on a stale setpoint must begin before its stop."""
    r = cfg.radio
    hold_s = r.stale_hold_slots / r.tx_rate_hz
    if hold_s >= r.stale_stop_s:
        return (f"radio.stale_stop_s = {r.stale_stop_s:g} s must be longer than radio.stale_hold_slots / "
                f"radio.tx_rate_hz = {hold_s:g} s")
    return None


def mpc_timing(cfg: Config) -> str | None:
    """Nodes no closer than a tick, and a horizon that sees the near future but not beyond reason."""
    c = cfg.controller
    tick = 1.0 / c.rate_hz
    if c.dt < tick:
        return f"controller.dt = {c.dt:g} s must be at least one control tick (1 / controller.rate_hz = {tick:g} s)"
    span = c.horizon * c.dt
    if not 0.1 <= span <= 10.0:
        return f"controller.horizon x controller.dt = {span:g} s is out of range: must be 0.1 to 10 s"
    return None


def solve_deadline(cfg: Config) -> str | None:
    tick = 1.0 / cfg.controller.rate_hz
    if cfg.safety.solve_deadline_s > tick:
        return (f"safety.solve_deadline_s = {cfg.safety.solve_deadline_s:g} s must be at most one control tick "
                f"(1 / controller.rate_hz = {tick:g} s)")
    return None


def tilt_order(cfg: Config) -> str | None:
    """A commanded tilt the tumble detector calls a tumble would stop the motors mid-manoeuvre."""
    if cfg.controller.max_tilt_deg >= cfg.safety.max_tilt_deg:
        return (f"controller.max_tilt_deg = {cfg.controller.max_tilt_deg:g} deg must be below "
                f"safety.max_tilt_deg = {cfg.safety.max_tilt_deg:g} deg (the tumble limit)")
    return None


def fence_order(cfg: Config) -> str | None:
    s = cfg.safety
    for axis, lo, hi in zip("xyz", s.fence_min, s.fence_max):
        if lo >= hi:
            return f"safety.fence_min {axis} = {lo:g} m must be below safety.fence_max {axis} = {hi:g} m"
    return None


def touchdown_below_flight(cfg: Config) -> str | None:
    """A touchdown height at or above the flight height would cut the motors in the air."""
    if cfg.safety.touchdown_height >= cfg.trajectory.height:
        return (f"safety.touchdown_height = {cfg.safety.touchdown_height:g} m must be below "
                f"trajectory.height = {cfg.trajectory.height:g} m")
    return None


def rollback_order(cfg: Config) -> str | None:
    o = cfg.online
    if o.rollback_fallbacks > o.rollback_ticks:
        return (f"online.rollback_fallbacks = {o.rollback_fallbacks} must be at most "
                f"online.rollback_ticks = {o.rollback_ticks} (they are counted in that window)")
    return None


def fast_force_band(cfg: Config) -> str | None:
    """The fast force's band must be a band, and its upper edge well inside the plant's step rate."""
    (low, high), dt = cfg.sim.aero_terms.fast_band_hz, cfg.sim.dt
    if low >= high:
        return f"sim.aero_terms.fast_band_hz = [{low:g}, {high:g}] Hz must have its low edge below its high edge"
    if high > 0.25 / dt:
        return (f"sim.aero_terms.fast_band_hz high edge {high:g} Hz must be at most a quarter of the plant's "
                f"step rate (0.25 / sim.dt = {0.25 / dt:g} Hz)")
    return None


def one_wake(cfg: Config) -> str | None:
    """The realistic plant brings its own, measured wake: two wake models at once would add up."""
    if cfg.sim.aero == "realistic" and cfg.sim.downwash.enabled:
        return ("sim.downwash.enabled is the ideal plant's wake; with sim.aero = realistic the wake is "
                "sim.aero_terms.downwash (0 turns it off)")
    return None


CROSS_CHECKS: tuple[Callable[[Config], str | None], ...] = (
    hover_authority, battery_order, radio_rate, stale_order, mpc_timing, solve_deadline, tilt_order, fence_order,
    touchdown_below_flight, rollback_order, fast_force_band, one_wake,
)


def check_bounds(cfg: Config, where: str = "") -> None:
    """Raise ``ConfigError`` (one line; ``where`` prefixes it) at the first bound or cross-key problem."""
    problem = out_of_bounds(cfg)
    for check in CROSS_CHECKS:
        if problem is not None:
            break
        problem = check(cfg)
    if problem is not None:
        raise ConfigError(f"{where}{problem}")
