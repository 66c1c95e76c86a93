"""Settings of the flight package: the controller, the velocity estimator, the reference trajectory."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from cfknode.kernel.setting import setting
from cfknode.kernel.vehicle import Vec3


@dataclass(frozen=True)
class AdaptationTuning:
    """Gains and bounds of the fast adaptation layer (``cfknode.flight.adaptation.AdaptationSettings``)."""

    bandwidth_hz: float = setting(unit="Hz", low=0, high=50, open_low=True,
        doc="cut-off of the vertical disturbance estimate (dob) / the l1 output filter, between steps")
    bandwidth_xy_hz: float = setting(unit="Hz", low=0, high=50, open_low=True,
        doc="the same for x and y: mocap noise and attitude lag enter there, and wind changes slowly")
    predictor_gain: float = setting(unit="1/s", low=0, high=1000, open_low=True, doc="l1 velocity predictor feedback")
    adaptation_gain: float = setting(low=0, high=100000.0, doc="l1 adaptive law gain (1/s^2)")
    thrust_rate: float = setting(unit="1/s", low=0, high=200, doc="vertical error moved into the mass estimate")
    axis_rate: float = setting(unit="1/s", low=0, high=200,
        doc="x/y tilt effectiveness (measured vs commanded) learning rate; 0 = off")
    max_offset: float = setting(unit="m/s^2", low=0, high=20, open_low=True, doc="largest acceleration offset per axis")
    thrust_scale_bounds: tuple[float, float] = setting(unit="x nominal mass", low=0.1, high=10, open_low=True,
        doc="estimated mass / nominal")
    axis_gain_bounds: tuple[float, float] = setting(low=0.1, high=10, open_low=True,
        doc="delivered / commanded tilt (the attitude loop reaches 0.8-1.2)")
    stale_pose_s: float = setting(unit="s", low=0, high=1, open_low=True,
        doc="without a fresh mocap pose this long the estimates are frozen")
    rebase_window_s: float = setting(unit="s", low=0, high=2, open_low=True,
        doc="recent ticks the offset is re-fitted over at a model swap")
    thrust_lag_s: float | None = setting(unit="s", low=0, high=0.5,
        doc="motor thrust lag the observer models; null: chosen in flight (flight/adaptation/thrust_lag.py)")
    thrust_lag_candidates_s: tuple[float, ...] = setting(unit="s", low=0.001, high=0.5,
        doc="the lags chosen among, with vehicle.motor_time_constant, when thrust_lag_s is null")
    step_threshold: float = setting(low=0, high=1000,
        doc="vertical step detector (dob): alarm level of a CUSUM of the velocity surprise, in noise units; 0 = off")
    step_bandwidth_hz: float = setting(unit="Hz", low=0, high=50, open_low=True,
        doc="vertical cut-off for step_hold_s after an alarm, fast enough to track a mass step")
    step_thrust_rate: float = setting(unit="1/s", low=0, high=1000,
        doc="thrust_rate for step_hold_s after an alarm")
    step_hold_s: float = setting(unit="s", low=0, high=5,
        doc="how long the step bandwidth and rate last after an alarm")
    step_max_s: float = setting(unit="s", low=0, high=10, open_low=True,
        doc="a step is tracked at most this long after its first alarm; later alarms start a new step")
    wake_radius: float = setting(unit="m", low=0, high=2,
        doc="no heavier step is called while another drone is above within this distance (its wake); 0 = off")
    oracle_delay_s: float = setting(unit="s", low=0, high=1,
        doc="adaptation oracle (a bench reference) only: the true mass is told this late")
    output_bandwidth_hz: float = setting(unit="Hz", low=0, high=50,
        doc="dob: the vertical offset the MPC gets is the estimate low-passed again at this cut-off; 0: the estimate")
    output_bandwidth_xy_hz: float = setting(unit="Hz", low=0, high=50,
        doc="the same for x and y (0: the estimate itself)")
    offset_deadband: float = setting(unit="m/s^2", low=0, high=5,
        doc="a horizontal offset well below it is shrunk toward 0, smoothly (d^3/(d^2+b^2)); 0 = off")
    engage_level: float = setting(unit="m/s^2", low=0, high=2,
        doc="an axis's estimate acts once the error it sees there is above this (0 = always acts)")
    engage_slow_level: float = setting(unit="m/s^2", low=0, high=2, open_low=True,
        doc="... or once that error's mean over engage_slow_s is above this (a small one that persists)")
    engage_slow_s: float = setting(unit="s", low=0, high=60, open_low=True,
        doc="time constant of the mean engage_slow_level is compared with")
    release_s: float = setting(unit="s", low=0, high=60,
        doc="an axis lets go again after this long with both under half their levels")
    accel_cutoff_hz: float = setting(unit="Hz", low=0, high=40,
        doc="cut-off of the accelerometer's fast part of the offset (flight/adaptation/accel_path.py); 0 = off")
    accel_max_offset: float = setting(unit="m/s^2", low=0, high=20, open_low=True,
        doc="largest acceleration the fast path adds per axis")
    accel_stale_s: float = setting(unit="s", low=0, high=1, open_low=True,
        doc="with no usable accelerometer sample this long the fast path is withdrawn (100 Hz log: 10 ms apart)")
    model_coefficients: bool = setting(
        doc="with a KNODE model flying, adapt a per-axis weight on its residual and hand its constant to the layer")
    coefficient_bounds: tuple[float, float] = setting(low=0, high=5,
        doc="the model's per-axis weights are kept inside")
    coefficient_memory_s: float = setting(unit="s", low=0, high=600, open_low=True,
        doc="time constant of the weights' least-squares fit (older ticks are forgotten)")
    coefficient_prior: float = setting(unit="m/s^2", low=0, high=10, open_low=True,
        doc="a model residual varying by this much (RMS) weighs as much as the prior weight 1")
    model_mean_s: float = setting(unit="s", low=0, high=600, open_low=True,
        doc="time constant of the model's mean residual, which the layer takes (vertically: the thrust scale)")
    model_min_score: float = setting(unit="share", low=0, high=1,
        doc="beside the layer a model flies only on axes whose stored score (model beyond layer) is above this, else not")


@dataclass(frozen=True)
class ControllerConfig:
    kind: Literal["mpc", "knode-mpc", "geometric"] = setting(
        doc="mpc (nominal model) | knode-mpc (nominal + KNODE residual, needs model) | geometric")
    model: str = setting(doc="KNODE model file (cfknode train --out ...); setting it implies knode-mpc")
    rate_hz: float = setting(unit="Hz", low=50, high=1000, doc="loop rate: estimator + MPC + Mellinger every tick")
    horizon: int = setting(unit="nodes", low=2, high=200, doc="MPC nodes N")
    dt: float = setting(unit="s", low=0, high=0.5, open_low=True, doc="s between MPC nodes (1 s horizon, as the paper)")
    solver: Literal["rti", "ipopt"] = setting(doc="rti (one QP per tick, real time) | ipopt (converged reference)")
    qp_solver: Literal["qrqp", "osqp"] = setting(doc="CasADi conic plugin used by rti: qrqp | osqp")
    codegen: bool = setting(doc="compile the RTI step with the system C compiler (cached); falls back to the VM")
    q_position: Vec3 = setting(low=0, high=1000000.0, doc="stage weights on position error, per axis")
    q_velocity: Vec3 = setting(low=0, high=1000000.0, doc="stage weights on velocity error")
    r_acceleration: Vec3 = setting(low=0, high=1000000.0, open_low=True,
        doc="weights on commanded acceleration minus the reference's")
    terminal_scale: float = setting(low=0, high=1000, doc="terminal weight = terminal_scale * stage weight")
    max_tilt_deg: float = setting(unit="deg", low=5, high=60, doc="the attitude the Mellinger layer may ask for")
    min_thrust_fraction: float = setting(low=0, high=0.9,
        doc="lowest commanded thrust as a fraction of hover (a_z >= -(1 - f) g): keeps attitude authority")
    max_thrust_fraction: float = setting(low=0.5, high=1.0,
        doc="highest vertical thrust the MPC plans, as a fraction of the RPYT clamp's (a_z <= f T_max / m - g)")
    yaw_rate_gain: float = setting(unit="1/s", low=0, high=20, doc="proportional yaw tracking in the Mellinger layer")
    max_yaw_rate_deg: float = setting(unit="deg/s", low=0, high=360, open_low=True,
        doc="largest yaw rate the Mellinger layer commands")
    geometric_kp: Vec3 = setting(unit="N/m", low=0, high=10, open_low=True,
        doc="firmware Mellinger kp_xy, kp_z (docs/hardware.md#mellinger); geometric controller and MPC fallback")
    geometric_kd: Vec3 = setting(unit="N/(m/s)", low=0, high=5,
        doc="firmware Mellinger kd_xy, kd_z (docs/hardware.md#mellinger)")
    adaptation: Literal["none", "l1", "dob", "oracle"] = setting(
        doc="fast adaptation of what the model gets wrong: none | dob | l1 | oracle (simulation only)")
    adaptation_settings: AdaptationTuning
    cone_reserve_deg: float = setting(5.0, unit="deg", low=0, high=20,
        doc="tilt the thrust cone always leaves horizontal tracking at the clamp (fast adaptation only)")
    fall_guard_level: float = setting(3.0, unit="m/s^2", low=0, high=20,
        doc="no fast layer: a specific-force drop this far below the sent thrust's flies the clamp until the fall stops")
    cache_dir: str | None = setting(None, doc="folder for the MPC's compiled code (null: $XDG_CACHE_HOME/cfknode, "
                                               "else ~/.cache/cfknode)")


@dataclass(frozen=True)
class EstimatorConfig:
    process_accel_std: float = setting(unit="m/s^2", low=0, high=100, open_low=True,
        doc="white-acceleration process noise of the constant-velocity Kalman filter")
    position_std: float = setting(unit="m", low=1e-05, high=0.1, doc="mocap position noise assumed by the filter")
    latency: float = setting(unit="s", low=0, high=0.2,
        doc="mocap latency the estimator predicts across (0 = none assumed)")
    command_delay: float = setting(0.0, unit="s", low=0, high=0.2,
        doc="from a sent command to its acceleration: the MPC plans from the state this far ahead; 0 = off")
    command_delay_z: float | None = setting(None, unit="s", low=0, high=0.2,
        doc="the vertical axis's command delay (motors only, no attitude loop); null = command_delay")
    command_residual_tau: float = setting(0.0, unit="s", low=0, high=10,
        doc="time constant of the acceleration the commands leave unexplained (drag), added to the prediction; 0 = off")
    command_lag: float = setting(0.0, unit="s", low=0, high=1,
        doc="0: x/y fly the commands after command_delay; > 0: through a first-order lag of this time constant")
    attitude_lag: float = setting(0.17, unit="s", low=0, high=1,
        doc="lag of the commanded x/y acceleration the filter predicts with between frames; 0: at once")


@dataclass(frozen=True)
class TrajectoryConfig:
    kind: Literal["hover", "circle", "figure8", "line", "vertical"] = setting(
        doc="hover | circle | figure8 | line (back and forth along x) | vertical (up and down)")
    radius: float = setting(unit="m", low=0.05, high=5,
        doc="m (circle radius; figure-8 half-width; line or vertical amplitude)")
    speed: float = setting(unit="m/s", low=0.01, high=5,
        doc="tangential speed on the circle / peak-ish speed on the figure-8 / peak speed of a line or vertical")
    center: tuple[float, float] = setting(unit="m", low=-50, high=50, doc="world x y of the pattern")
    height: float = setting(unit="m", low=0.03, high=5, doc="flight altitude (below 0.1 m: a surface transit, in ground effect)")
    duration: float = setting(unit="s", low=0, high=3600, doc="s on the pattern (circle or figure-8) or in hover")
    takeoff_duration: float = setting(unit="s", low=0.5, high=60,
        doc="smooth climb from the start pose to the pattern's first point")
    settle_duration: float = setting(unit="s", low=0, high=60, doc="hover at the pattern start before it begins")
    land_duration: float = setting(unit="s", low=0.5, high=60, doc="smooth descent to the ground")
    ramp_duration: float = setting(unit="s", low=0, high=60,
        doc="speed ramp-in at the start of the pattern (0 = step to full speed)")
