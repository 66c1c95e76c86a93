"""Fast adaptation: what the flying model (nominal, or nominal + KNODE residual) still gets wrong, every tick.

Three estimates, relative to the model's predicted acceleration for the command actually applied:
- ``offset`` d (3, m/s^2): an additive acceleration error, handed to the MPC as a residual constant (integral action);
- ``thrust_scale`` s: mass / nominal mass as the thrust sees it; the Mellinger layer computes thrust with s m;
- ``axis_gain`` k (x, y, 1): how much of a commanded tilt the attitude loop delivers; the Mellinger layer divides by it.
A disturbance estimate sigma comes from an observer on velocity (no differentiation of v), whose input is the thrust
actually sent along the *measured* body axis (the attitude loop's lag is then not a disturbance: fed the commanded
acceleration instead, the 2 Hz observer and the MPC oscillated through that lag). Its vertical part is moved into s,
shifting sigma so that model + layer predicts the same acceleration before and after; what remains is d. k compares
the horizontal acceleration the measured attitude gives with the one commanded.

Method choice (paper cell, mass 0.5x then 1.33x, both at 4 Hz / thrust rate 6): "dob" (first-order disturbance
observer) MSE 0.0019, "l1" (velocity predictor + adaptive law + output filter) 0.0059 with a 0.40 m sag against 0.25:
the l1 filter chain adds lag for no gain here. "dob" is the method; "l1" stays for comparison.

No single bandwidth serves both a noisy mocap and a payload step (6 Hz: 1.4e-3 m^2 on the lab circle
with 2 mm of noise; 2 Hz: a 0.49 m sag at 1.33x mass). So the observer is slow between steps and a step
detector raises an alarm: a CUSUM of the frame-to-frame vertical velocity surprise, normalised by its noise
level learned in flight. For ``step_hold_s`` after it the mass is fitted to the mocap heights around the
onset (step_fit.py), which does not ring as the observer moving an additive estimate into the mass did
(0.40-0.74 for a true 0.5); a fit that sees no step keeps the mass. Without heights the observer runs at
``step_bandwidth_hz`` instead, with the run's unexplained acceleration added at the alarm. See
docs/results.md#fast-adaptation.

What the MPC gets is not sigma itself (dob): sigma = omega (v - z) passes the velocity estimate's noise straight
through at gain omega, and in quiet flight that noise was the whole offset (0.027 m/s^2 rms horizontally) and
cost 17 % MSE on the lab circle. The published offset is sigma behind a second low-pass pole (``output_bandwidth``;
bypassed vertically while a step is tracked), and horizontally shrunk where it is not clearly above
``offset_deadband``: the few mm/s^2 left at the circle's frequency follow the attitude measurement's age and the
attitude loop's response, dynamics the MPC cannot cancel as a constant. The thrust scale learns from the
smoothed vertical estimate too (at 2 mm of mocap noise the raw one shook it: z MSE 1.05e-6 against 3.0e-7).

What the controller flies with is ``applied``: the estimate on the axes where it acts, the model alone on the
others (``engagement``). An axis acts once the error the layer sees there (its offset; vertically the offset plus
the mass estimate's share at hover) is above ``engage_level``, or its slow mean above ``engage_slow_level``, and
lets go after ``release_s`` with both under half their levels. On a plant the model matches, the estimate is
noise and unmodelled dynamics (up to 0.077 m/s^2 at 2 mm of mocap noise, its 2 s mean 0.019), and acting on it
cost 0.1-6 % over plain MPC; now such a flight is plain MPC's to the last digit. A step, a wind or a thrust-map
error is far above the level within a fraction of a second, a 0.4-0.7 % mass error through the slow mean
within seconds. The cost: an error under about 0.3 % is left to the MPC (1.5 mm of height on the lab circle).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from cfknode.flight.imu_step import ImuStepDetector
from cfknode.flight.step_fit import LAG_FRAMES, StepFit

MODES = ("none", "l1", "dob")
Mode = Literal["none", "l1", "dob"]


@dataclass(frozen=True)
class AdaptationSettings:
    mode: Mode
    bandwidth_hz: float  # low-pass cut-off of the vertical disturbance estimate (dob) / of the l1 output filter
    bandwidth_xy_hz: float  # the same for x and y: lower, since mocap noise enters there as tilt jitter
    predictor_gain: float  # 1/s, l1: velocity predictor's error feedback
    adaptation_gain: float  # 1/s^2, l1: adaptive law gain (the fast inner estimate)
    thrust_rate: float  # 1/s: how fast the vertical error moves into thrust_scale
    axis_rate: float  # 1/s: how fast horizontal command-proportional error moves into axis_gain
    max_offset: float  # m/s^2 per axis
    thrust_scale_bounds: tuple[float, float]
    axis_gain_bounds: tuple[float, float]
    stale_pose_s: float  # s without a fresh mocap pose: frozen
    rebase_window_s: float  # s of recent ticks the re-base at a model swap averages over
    thrust_lag_s: float | None = None  # s, first-order lag from the thrust sent to the thrust acting (None: chosen)
    thrust_lag_candidates_s: tuple[float, ...] = (0.015, 0.04, 0.08, 0.15)  # s, the lags chosen among when None
    step_threshold: float = 0.0  # alarm level of the vertical step detector (CUSUM of noise-normalised surprise); 0 off
    step_bandwidth_hz: float = 10.0  # vertical cut-off while a detected step is being tracked
    step_thrust_rate: float = 400.0  # 1/s, thrust_rate while a detected step is being tracked
    step_hold_s: float = 0.3  # s after an alarm at the step bandwidth and rate
    oracle_delay_s: float = 0.0  # s, the oracle reference only (adaptation_oracle.py)
    output_bandwidth_hz: float = 0.0  # dob: the vertical offset is sigma low-passed again at this cut-off; 0 sigma itself
    output_bandwidth_xy_hz: float = 0.0  # the same for x and y
    offset_deadband: float = 0.0  # m/s^2: a horizontal offset well below it is shrunk toward 0 (see shrink); 0 off
    engage_level: float = 0.0  # m/s^2: an axis acts once its evidence is above this (see engagement); 0: always
    engage_slow_level: float = math.inf  # m/s^2: ... or once the evidence's slow mean is above this
    engage_slow_s: float = 2.0  # s, time constant of that mean
    release_s: float = 1.0  # s with both under half their levels before an axis lets go again

    @property
    def enabled(self) -> bool:
        return self.mode != "none"


@dataclass(frozen=True)
class AdaptationEstimate:
    offset: np.ndarray  # (3,) m/s^2, added to the model's acceleration
    thrust_scale: float  # estimated mass / nominal mass
    axis_gain: np.ndarray  # (3,) delivered / commanded horizontal acceleration (z is 1)
    frozen: bool = False  # no update this tick (stale pose or not flying)
    saturated: bool = False  # the last applied command was at the thrust clamp or the tilt limit
    stepping: bool = False  # a vertical step was detected and is being tracked at the step bandwidth
    acts: tuple[bool, bool, bool] = (True, True, True)  # x, y, vertical: the estimate acts there (see engagement)

    @classmethod
    def neutral(cls) -> AdaptationEstimate:
        return cls(np.zeros(3), 1.0, np.ones(3))

    def to_log(self) -> dict[str, object]:
        return {"offset": self.offset, "thrust_scale": self.thrust_scale, "axis_gain": self.axis_gain[:2],
                "frozen": self.frozen, "saturated": self.saturated, "stepping": self.stepping, "acts": list(self.acts)}


# ---------------------------------------------------------------- pure math

def dob_step(z: np.ndarray, v: np.ndarray, a_model: np.ndarray, omega: np.ndarray | float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """First-order disturbance observer: sigma = omega (v - z), z' = a_model + sigma.

    sigma is the low-pass (cut-off omega) of v' - a_model without differentiating v. Returns (z, sigma)."""
    sigma = omega * (v - z)
    return z + dt * (a_model + sigma), sigma


def l1_step(
    v_hat: np.ndarray, sigma_hat: np.ndarray, sigma_f: np.ndarray, v: np.ndarray, a_model: np.ndarray,
    k_pred: float, gamma: float, omega: np.ndarray | float, dt: float, bound: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """L1-style: velocity predictor, gradient adaptive law with projection (a box), low-pass output filter."""
    err = v_hat - v
    sigma_hat = np.clip(sigma_hat - dt * gamma * err, -bound, bound)
    v_hat = v_hat + dt * (a_model + sigma_hat - k_pred * err)
    sigma_f = sigma_f + np.minimum(1.0, dt * omega) * (sigma_hat - sigma_f)
    return v_hat, sigma_hat, sigma_f


def smooth_step(out: np.ndarray, sigma: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """The published offset: ``sigma`` low-passed at ``omega`` (rad/s per axis; inf passes sigma through).

    The observer's sigma = omega (v - z) carries the velocity estimate's noise at gain omega, unfiltered: in
    quiet flight it is that noise (a 0.5 Hz horizontal sigma was 0.027 m/s^2 rms, 96 % of it above 5 Hz, with a
    0.999 correlation to omega times the velocity error). Behind this second pole it rolls off as 1/f."""
    return out + np.minimum(1.0, omega * dt) * (sigma - out)


def shrink(offset: np.ndarray, band: float) -> np.ndarray:
    """``offset`` with what is not clearly above ``band`` (m/s^2) taken out, smoothly: d^3 / (d^2 + band^2).

    Below the band the value falls off as d^3 (a quiet flight's few mm/s^2 of residual dynamics and noise do
    not reach the MPC); well above it the value passes with a bias of band^2 / d."""
    if band <= 0.0:
        return offset
    sq = offset * offset
    return offset * sq / (sq + band * band)


def thrust_transfer(sigma_z: float, u_z: float, g: float, scale: float, rate: float, dt: float,
                    bounds: tuple[float, float]) -> float:
    """New thrust scale, moved toward the one that explains the vertical error ``sigma_z`` at command ``u_z``.

    With thrust from s m, the plant gives a_z + g = (s / theta)(u_z + g); sigma_z = 0 at s = theta."""
    lift = u_z + g
    if lift < 0.3 * g:  # too little thrust to tell a mass from an offset
        return scale
    target = scale * lift / max(lift + sigma_z, 0.1 * g)
    step = min(1.0, rate * dt)
    return float(np.clip(scale + step * (target - scale), *bounds))


def axis_transfer(sigma_xy: float, u_xy: float, gain: float, rate: float, dt: float,
                  bounds: tuple[float, float], u_min: float = 0.5) -> float:
    """New axis gain from the part of ``sigma_xy`` proportional to the command ``u_xy`` (normalised gradient)."""
    if abs(u_xy) < u_min:  # no excitation: an offset there is wind, not effectiveness
        return gain
    target = gain * (u_xy + sigma_xy) / u_xy
    step = min(1.0, rate * dt)
    return float(np.clip(gain + step * (target - gain), *bounds))


def sigma_after_transfer(sigma: np.ndarray, u: np.ndarray, g: float, s_old: float, s_new: float) -> np.ndarray:
    """sigma once the thrust scale changed, so model + layer predicts the same acceleration.

    A larger s sends more thrust for the same u (the plant does more): sigma grows by (ds / s)(u + g e_z + sigma)."""
    force = u + np.array([0.0, 0.0, g]) + sigma
    return sigma + (s_new / s_old - 1.0) * force


def rebase_offset(offset: np.ndarray, old_acc: np.ndarray, new_acc: np.ndarray, bound: float) -> np.ndarray:
    """Offset after a model swap: shifted by the mean of (old - new) model acceleration over recent ticks,
    so the sum model + offset is unchanged on average where the vehicle just flew."""
    if old_acc.shape[0] == 0:
        return offset
    shift = np.mean(old_acc - new_acc, axis=0)
    if not np.all(np.isfinite(shift)):
        return offset
    return np.clip(offset + shift, -bound, bound)


def engagement(engaged: np.ndarray, quiet: np.ndarray, evidence: np.ndarray, slow: np.ndarray, level: float,
               slow_level: float, release_s: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Per axis (x, y, vertical): (acts, seconds its evidence has been quiet).

    An axis acts once its evidence (m/s^2 the model gets wrong there) is above ``level``, or the evidence's
    slow mean ``slow`` above ``slow_level`` (a small error that persists), and lets go after ``release_s`` with
    both under half their levels; ``level`` 0: every axis always acts. On a plant the model matches, the
    estimate is the velocity's noise and unmodelled dynamics that no constant cancels: acting on it cost
    plain MPC 0.1-6 % on quiet plants."""
    if level <= 0.0:
        return np.ones(3, dtype=bool), np.zeros(3)
    size, mean = np.abs(evidence), np.abs(slow)
    quiet = np.where((size < 0.5 * level) & (mean < 0.5 * slow_level), quiet + dt, 0.0)
    return (engaged | (size > level) | (mean > slow_level)) & (quiet < release_s), quiet


def applied_estimate(estimate: AdaptationEstimate, acts: np.ndarray) -> AdaptationEstimate:
    """What the controller flies with: ``estimate`` on the axes that act, the model alone on the others
    (offset 0; thrust scale 1 and axis gain 1 where the vertical / that horizontal axis does not act)."""
    if acts.all():
        return estimate
    gain = np.where(np.array([acts[0], acts[1], True]), estimate.axis_gain, 1.0)
    return replace(estimate, offset=np.where(acts, estimate.offset, 0.0),
                   thrust_scale=estimate.thrust_scale if acts[2] else 1.0, axis_gain=gain,
                   acts=(bool(acts[0]), bool(acts[1]), bool(acts[2])))


STEP_DRIFT = 0.5  # CUSUM drift, in noise std: surprise below half a std never accumulates
NOISE_FRAMES = 100  # mocap frames the surprise noise level averages over (1 s at 100 Hz)
NOISE_FLOOR = 1e-4  # m/s per frame: below this the surprise is numerics, not noise
# Alarms in a row are no step: the plant responds otherwise than modelled (a slower motor, say), and the fast
# estimate would ring on it. An alarm within REARM_S of the last one's end doubles the threshold (up to
# MAX_THRESHOLD_SCALE); QUIET_RESET_S without an alarm restores it.
REARM_S = 1.0
MAX_THRESHOLD_SCALE = 16.0
QUIET_RESET_S = 10.0


def cusum_step(g: tuple[float, float], z: float, drift: float = STEP_DRIFT) -> tuple[float, float]:
    """Two-sided CUSUM on the normalised surprise ``z``: (upward, downward) sums, each floored at 0."""
    return max(0.0, g[0] + z - drift), max(0.0, g[1] - z - drift)


# ---------------------------------------------------------------- state


class FastAdaptation:
    """The estimator's state; ``update`` once per tick before the MPC solves."""

    def __init__(self, settings: AdaptationSettings, rate_hz: float, gravity: float = 9.81) -> None:
        if settings.mode not in MODES:
            raise ValueError(f"unknown adaptation mode {settings.mode!r}; expected one of {', '.join(MODES)}")
        self.s = settings
        self.g = gravity
        self.dt = 1.0 / rate_hz
        self.omega = 2.0 * math.pi * np.array([settings.bandwidth_xy_hz, settings.bandwidth_xy_hz, settings.bandwidth_hz])
        self.omega_step = 2.0 * math.pi * max(settings.step_bandwidth_hz, settings.bandwidth_hz)
        # The published offset's low-pass (dob): sigma = omega (v - z) passes the velocity estimate's noise
        # straight through at gain omega; a second pole makes that roll off (see smooth_step).
        out_hz = np.array([settings.output_bandwidth_xy_hz, settings.output_bandwidth_xy_hz, settings.output_bandwidth_hz])
        self.omega_out = np.where(out_hz > 0.0, 2.0 * math.pi * out_hz, math.inf)  # inf: sigma itself
        self._omega_out_step = np.array([self.omega_out[0], self.omega_out[1], math.inf])
        n = max(1, int(round(settings.rebase_window_s * rate_hz)))
        self._buf_x = np.zeros((n, 6))
        self._buf_u = np.zeros((n, 3))
        self._buf_a = np.zeros((n, 3))
        self._buf_len = 0
        self._buf_i = 0
        self.resets = 0
        self.rebases = 0
        self.steps = 0  # vertical steps detected
        self.fits = 0  # frames at which a step's mass was re-fitted
        self.imu_steps = 0  # steps the accelerometer raised first
        self._fit = StepFit(rate_hz)
        self._imu = ImuStepDetector()
        self.reset()

    def reset(self) -> None:
        """Back to the model alone (take-off, landing, non-finite input)."""
        self.estimate = AdaptationEstimate.neutral()
        self._quiet = np.zeros(3)
        self._slow = np.zeros(3)  # the evidence's slow mean
        self.acts = np.full(3, self.s.engage_level <= 0.0)  # level 0: every axis always acts
        self.applied = applied_estimate(self.estimate, self.acts)  # what the controller flies with (see engagement)
        self._sigma = np.zeros(3)
        self._out = np.zeros(3)  # the published offset before its bound and the saturation hold
        self._obs: np.ndarray | None = None  # dob z or l1 v_hat; None: re-synchronise on the next update
        self._sigma_hat = np.zeros(3)
        self._last_fresh_t = -math.inf
        self._t_prev: float | None = None
        self._buf_len = self._buf_i = 0
        self._cusum = (0.0, 0.0)
        self._noise_var = 0.0  # (m/s)^2 per frame: the vertical surprise's noise
        self._v_prev: float | None = None
        self._step_until = -math.inf
        self._omega_z = float(self.omega[2])  # the vertical bandwidth the observer's state is scaled for
        self._frames = 0  # mocap frames the detector has seen since the reset
        self._frame_surprise = 0.0
        self._t_frame: float | None = None
        self._run = [[0.0, 0.0], [0.0, 0.0]]  # per CUSUM side: summed surprise (m/s) and its span (s)
        self._jump = 0.0  # m/s^2 added to the vertical estimate at an alarm
        self._threshold_scale = 1.0
        self._last_alarm = -math.inf
        self._fit.reset()
        self._onset_hint: float | None = None  # s, the frame before the alarm's run began
        self._fitted: tuple[float, float, bool] | None = None  # (thrust scale, vertical offset, significant)
        self._frame_dt = 0.01  # s between mocap frames, learned
        self._fitting = False  # heights are given: steps are fitted
        self.fit_lag: int | None = None  # the motor lag (an index of ``thrust_by_lag``) the last significant fit chose
        self._imu.reset()
        self._imu_step = False  # the step being tracked was raised by the accelerometer
        self._imu_sigma = 0.0  # the vertical offset when it was
        self._fit_frames = 0  # frames after the onset in the step's latest height fit
        self._theta_at_alarm = 1.0  # 1 / thrust scale when the frames' detector raised its alarm
        self._vetoed = False  # the accelerometer saw no step in this hold of the frames' detector
        self.resets += 1

    def update(
        self, t: float, v_meas: np.ndarray, x_meas: np.ndarray | None, u_applied: np.ndarray, model_acc: np.ndarray,
        saturated: tuple[bool, bool] = (False, False), pose_fresh: bool = True, u_commanded: np.ndarray | None = None,
        thrust_by_lag: np.ndarray | None = None, lag: int = 0, imu_theta: tuple[float, float] | None = None,
    ) -> AdaptationEstimate:
        """One tick. ``u_applied`` / ``model_acc`` are the previous tick's command as the vehicle flew it (sent
        thrust along the measured body axis, in the model's input space) and the model's acceleration for it;
        ``saturated`` is (thrust at the clamp, tilt limited) for that command; ``u_commanded`` is what the
        Mellinger layer was asked for (after its limits), for the axis gains. ``thrust_by_lag``: the acting
        thrust's vertical acceleration over the nominal mass under each candidate motor lag, ``lag`` the one
        ``u_applied`` used (a step's fit then tells the lag too: ``fit_lag``). ``imu_theta``: (time, theta) of an
        accelerometer sample new this tick, its specific force over the acting thrust's per nominal mass
        (imu_step.py). Returns the estimate for this tick."""
        if not self.s.enabled:
            return self.estimate
        if not (np.all(np.isfinite(v_meas)) and np.all(np.isfinite(u_applied)) and np.all(np.isfinite(model_acc))):
            self.reset()
            return self.estimate
        if pose_fresh:
            self._last_fresh_t = t
        stalled = self.stalled(t)
        dt = self.dt if self._t_prev is None else min(max(t - self._t_prev, 0.0), 0.05)
        self._t_prev = t
        stale = t - self._last_fresh_t > self.s.stale_pose_s or stalled
        thrust_sat, tilt_sat = saturated
        if stale or self._obs is None or dt <= 0.0:
            self._sync(v_meas)  # nothing learned while blind: the predictor restarts from the measurement
            self._v_prev = None
            self._fit.reset()
            self.estimate = replace(self.estimate, frozen=True, saturated=thrust_sat or tilt_sat)
            self.applied = applied_estimate(self.estimate, self.acts)
            return self.estimate

        self._fitting = self.s.mode == "dob" and self.s.step_threshold > 0.0 and x_meas is not None
        if self._fitting:
            scale = self.estimate.thrust_scale  # u_applied's thrust was divided by it: a_T is what the motors did
            a_thrust = (float(u_applied[2]) + self.g) * scale if thrust_by_lag is None else thrust_by_lag
            self._fit.tick(t, float(x_meas[2]), a_thrust, float(model_acc[2] - u_applied[2]) - self.g, 1.0 / scale,
                           float(self._out[2]), pose_fresh, lag)
        if self._fitting and imu_theta is not None:
            self._imu_sample(t, *imu_theta)
        stepping = self._detect_step(t, float(v_meas[2]), float(model_acc[2]), dt, thrust_sat, pose_fresh)
        fit = self._refit(stepping, pose_fresh)
        if fit is not None:
            self._jump = 0.0  # the fit tells whether there was a step; the run's mean acceleration is not added
        omega = self.omega if not stepping else np.array([self.omega[0], self.omega[1], self.omega_step])
        if self.s.mode == "dob":
            if omega[2] != self._omega_z or self._jump:  # switch: rescale so that sigma continues (+ the jump)
                self._sigma = self._sigma.copy()
                self._sigma[2] = float(np.clip(self._sigma[2] + self._jump, -self.s.max_offset, self.s.max_offset))
                self._jump = 0.0
                self._obs = self._obs.copy()
                self._obs[2] = v_meas[2] - self._sigma[2] / omega[2]
                self._omega_z = float(omega[2])
            self._obs, new_sigma = dob_step(self._obs, v_meas, model_acc, omega, dt)
        else:
            self._obs, self._sigma_hat, new_sigma = l1_step(
                self._obs, self._sigma_hat, self._sigma, v_meas, model_acc,
                self.s.predictor_gain, self.s.adaptation_gain, self.omega, dt, self.s.max_offset + 5.0)
        # Anti-windup, first half: the observer is fed the command as flown (clamped thrust, limited tilt), so
        # the gap between what was asked and what the limits let through is never integrated as a disturbance.
        # Projection: the estimate stays in its box (the observer is told, so it does not wind up beyond it).
        bounded = np.clip(new_sigma, -self.s.max_offset, self.s.max_offset)
        if np.any(bounded != new_sigma):
            self._shift_observer(bounded - new_sigma, omega)
        self._sigma = bounded
        if self.s.mode == "dob":  # a tracked step is published as fast as the observer learns it
            self._out = smooth_step(self._out, bounded, self._omega_out_step if stepping else self.omega_out, dt)
        else:
            self._out = bounded
        fitted_scale = None
        if fit is not None:  # the fitted mass, or the one before the onset if the frames show no step; either
            fitted_scale = fit[0]  # way the vertical offset stays what it was before the onset
            self._sigma[2] = self._out[2] = fit[1]
            if self.s.mode == "dob":
                self._obs[2] = v_meas[2] - fit[1] / omega[2]
        self._settle(u_applied, u_commanded, thrust_sat, tilt_sat, dt, stepping, omega, fitted_scale)
        self._remember(x_meas if x_meas is not None else np.concatenate((np.zeros(3), v_meas)), u_applied, model_acc)
        return self.estimate

    def stalled(self, t: float) -> bool:
        """Whether the layer's last tick is longer ago than a stale pose (a stalled host): a blind spell too. The
        vehicle moved meanwhile, and integrating across the gap read that motion as a disturbance (+-6 m/s^2
        after 0.59 s)."""
        return self._t_prev is not None and t - self._t_prev > self.s.stale_pose_s

    def _detect_step(self, t: float, v_z: float, a_z: float, dt: float, thrust_sat: bool, fresh: bool) -> bool:
        """True while a vertical step (a mass change, a payload) is being tracked fast.

        The surprise is the vertical velocity change that the model plus the current estimate did not predict,
        summed from one mocap frame to the next (between frames the velocity is a prediction: only frames carry
        news). Its noise level is learned in flight, so one threshold holds at 0.3 and at 2 mm of mocap noise; a
        CUSUM of the normalised frame surprise raises the alarm: noise averages out, a step adds up."""
        if self.s.step_threshold <= 0.0 or self.s.mode != "dob":
            return False
        v_prev, self._v_prev = self._v_prev, v_z
        stepping = t < self._step_until
        if v_prev is None:
            return stepping
        self._frame_surprise += v_z - v_prev - dt * (a_z + float(self._sigma[2]))
        if not fresh:
            return stepping
        surprise, self._frame_surprise = self._frame_surprise, 0.0
        # The noise level is learned all the time (a step's few large surprises move it little); alarms wait
        # until it has seen a window of frames.
        self._frames += 1
        k = 1.0 / min(self._frames, NOISE_FRAMES)
        self._noise_var = (1.0 - k) * self._noise_var + k * surprise * surprise
        if self._frames < NOISE_FRAMES:
            return stepping
        std = math.sqrt(max(self._noise_var, NOISE_FLOOR ** 2))
        before = self._cusum
        self._cusum = cusum_step(self._cusum, surprise / std)
        # What each side's run has not been explained: summed surprise and its duration since that sum left 0.
        for i in (0, 1):
            if before[i] <= 0.0:
                self._run[i] = [0.0, 0.0]
            if self._cusum[i] > 0.0:
                self._run[i][0] += surprise
                self._run[i][1] += t - self._t_frame if self._t_frame is not None else 0.0
        if self._t_frame is not None:
            self._frame_dt += 0.05 * (min(t - self._t_frame, 0.1) - self._frame_dt)
        self._t_frame = t
        side = 0 if self._cusum[0] >= self._cusum[1] else 1
        if t - self._last_alarm > QUIET_RESET_S:
            self._threshold_scale = 1.0
        if self._cusum[side] > self.s.step_threshold * self._threshold_scale and not thrust_sat:
            if not stepping:
                if t - self._step_until < REARM_S:
                    self._threshold_scale = min(2.0 * self._threshold_scale, MAX_THRESHOLD_SCALE)
                dv, span = self._run[side]
                if span > 0.0:  # the run's mean unexplained acceleration joins the estimate at once
                    self._jump = dv / span
                self._start_step(t, t - span, by_imu=False)
                self.steps += 1
            if not (stepping and self._vetoed):
                self._step_until = t + self.s.step_hold_s
            self._cusum = (0.0, 0.0)
            self._run = [[0.0, 0.0], [0.0, 0.0]]
            return True
        return stepping

    def _imu_sample(self, t: float, t_sample: float, theta: float) -> None:
        """An accelerometer sample: a step it sees starts the step's tracking at once, from its onset. A hold the
        frames' detector raised does not stop it: that alarm can be a false one just before a real step (a
        0.5x step 76 ms after one went unseen, and the fit searched for its onset at the false alarm's)."""
        stepping = t < self._step_until and self._imu_step
        onset = self._imu.sample(t_sample, theta, 1.0 / self.estimate.thrust_scale, stepping)
        if onset is None:
            return
        self.steps += int(t >= self._step_until)  # within a hold of the frames' detector: the same step, now seen
        self.imu_steps += 1
        self._start_step(t, onset, by_imu=True)
        self._step_until = t + self.s.step_hold_s
        self._cusum = (0.0, 0.0)
        self._run = [[0.0, 0.0], [0.0, 0.0]]
        self._fitted = None  # a fit around another onset says nothing about this one

    def _start_step(self, t: float, onset: float, by_imu: bool) -> None:
        """What either detector's alarm sets: the onset the fit searches near, and what the hold starts from."""
        self._last_alarm = t
        self._onset_hint = onset
        self._fit_frames = 0
        self._vetoed = False
        self._imu_step = by_imu
        self._imu_sigma = float(self._out[2])
        self._theta_at_alarm = 1.0 / self.estimate.thrust_scale

    def _refit(self, stepping: bool, fresh: bool) -> tuple[float, float, bool] | None:
        """While a step is tracked with heights, refined each frame: (thrust scale, offset before the onset,
        significant) fitted to the frames around the onset. Not significant (a false alarm), or too few frames
        yet: the scale and offset of before the onset, held. None without heights: the observer tracks it."""
        if not stepping or self._onset_hint is None or not self._fitting:  # no heights: the observer tracks it
            self._fitted = None
            self._imu_step = False
            return None
        if fresh:
            got = self._fit.estimate(self._onset_hint, self._frame_dt)
            if (got is not None and got.significant and not self._imu_step
                    and self._imu.sees_no_change(self._onset_hint, self._theta_at_alarm)):
                # The frames' alarm and the accelerometer sees no step: a glitch, or an error that was there
                # before (a mass still being learned). The mass stays, and the hold is not extended by more
                # of the frames' alarms, so the slow observer learns such an error once the hold ends.
                got = replace(got, theta=self._theta_at_alarm, significant=False)
                self._vetoed = True
            if got is not None:
                self._fitted = (float(np.clip(1.0 / got.theta, *self.s.thrust_scale_bounds)), got.sigma, got.significant)
                self.fits += int(got.significant)
                self.fit_lag = got.lag if got.significant else None
                self._fit_frames = got.frames
        # Raised by the accelerometer: its samples tell the mass until the heights have as many frames as a lag
        # needs (a height fit on a few frames is the noisier one); the heights then say whether there was a step.
        imu = self._imu.theta() if self._imu_step else None
        if imu is not None and self._fit_frames < LAG_FRAMES:
            sigma0 = self._fitted[1] if self._fitted is not None else self._imu_sigma
            self._fitted = (float(np.clip(1.0 / imu, *self.s.thrust_scale_bounds)), sigma0, True)
        if self._fitted is None:  # too few frames yet: the estimate holds still rather than guess
            self._fitted = (self.estimate.thrust_scale, float(self._sigma[2]), False)
        return self._fitted

    def _settle(self, u: np.ndarray, u_cmd: np.ndarray | None, thrust_sat: bool, tilt_sat: bool, dt: float,
                stepping: bool = False, omega: np.ndarray | None = None, fitted_scale: float | None = None) -> None:
        """Move sigma into the thrust scale, update the axis gains, then publish the remaining offset (bounded)."""
        est, s = self.estimate, self.s
        scale, gain = est.thrust_scale, est.axis_gain.copy()
        sigma = self._sigma
        # Moving held error into s is no integration: it changes no prediction (see sigma_after_transfer).
        rate = s.step_thrust_rate if stepping else s.thrust_rate
        if fitted_scale is not None:  # a fitted step sets the scale; sigma was pinned by the caller
            new_scale = scale = fitted_scale
        else:
            new_scale = thrust_transfer(float(self._out[2]), float(u[2]), self.g, scale, rate, dt,
                                        s.thrust_scale_bounds)
        new_gain = gain.copy()
        if u_cmd is not None and not tilt_sat and s.axis_rate > 0.0:
            for i in (0, 1):  # delivered / commanded horizontal acceleration: the attitude loop's effectiveness
                new_gain[i] = axis_transfer(float(u[i] - u_cmd[i]), float(u_cmd[i]), gain[i], s.axis_rate, dt,
                                            s.axis_gain_bounds)
        if new_scale != scale:
            moved = sigma_after_transfer(sigma, u, self.g, scale, new_scale)
            self._shift_observer(moved - sigma, omega)
            self._sigma = moved
        offset = self._published()
        # Second half: on a saturated axis the MPC's offset is held; a growing one would only push the plan
        # further into a limit it cannot act beyond (the mass estimate keeps learning from the flown thrust).
        hold = np.array([tilt_sat, tilt_sat, thrust_sat])
        if hold.any():
            offset = np.where(hold, est.offset, offset)
        self.estimate = AdaptationEstimate(offset, new_scale, new_gain, frozen=False, saturated=thrust_sat or tilt_sat,
                                           stepping=stepping)
        self._engage(dt)

    def _engage(self, dt: float) -> None:
        """Which axes act, from the evidence: the horizontal offsets before their shrink, and vertically the
        offset plus what the mass estimate moved out of it (its error at hover)."""
        out = np.clip(self._out, -self.s.max_offset, self.s.max_offset)
        evidence = np.array([out[0], out[1], out[2] + (self.estimate.thrust_scale - 1.0) * self.g])
        self._slow = self._slow + min(1.0, dt / self.s.engage_slow_s) * (evidence - self._slow)
        self.acts, self._quiet = engagement(self.acts, self._quiet, evidence, self._slow, self.s.engage_level,
                                            self.s.engage_slow_level, self.s.release_s, dt)
        self.applied = applied_estimate(self.estimate, self.acts)

    def _published(self) -> np.ndarray:
        """The offset the MPC gets: bounded, the horizontal part shrunk (the vertical one is kept small by the
        thrust-scale transfer, and a shrink there would lag a ramp such as a battery's sag)."""
        offset = np.clip(self._out, -self.s.max_offset, self.s.max_offset)
        offset[:2] = shrink(offset[:2], self.s.offset_deadband)
        return offset

    def _shift_observer(self, d_sigma: np.ndarray, omega: np.ndarray | None = None) -> None:
        """Make the observer report sigma + d_sigma from now on (its prediction continues from there); the
        published offset moves with it (a re-expression, not news)."""
        self._out = self._out + d_sigma
        if self._obs is None:
            return
        if self.s.mode == "dob":
            self._obs = self._obs - d_sigma / (self.omega if omega is None else omega)
        else:
            self._sigma_hat = self._sigma_hat + d_sigma

    def _sync(self, v: np.ndarray) -> None:
        if self.s.mode == "dob":
            self._obs = v - self._sigma / self.omega
            self._omega_z = float(self.omega[2])
        else:
            self._obs = v.copy()
            self._sigma_hat = self._sigma.copy()

    def _remember(self, x: np.ndarray, u: np.ndarray, a: np.ndarray) -> None:
        i = self._buf_i
        self._buf_x[i], self._buf_u[i], self._buf_a[i] = x, u, a
        self._buf_i = (i + 1) % self._buf_x.shape[0]
        self._buf_len = min(self._buf_len + 1, self._buf_x.shape[0])

    def recent(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The buffered recent ticks: states (n, 6), applied commands (n, 3), the flying model's accelerations (n, 3)."""
        n = self._buf_len
        return self._buf_x[:n].copy(), self._buf_u[:n].copy(), self._buf_a[:n].copy()

    def rebase(self, new_model_acc: np.ndarray) -> AdaptationEstimate:
        """A model swap: ``new_model_acc`` (n, 3) is the NEW model's acceleration on ``recent()``'s ticks.

        The offset absorbs the difference so model + layer is continuous; the learner's model takes over what it
        explains and the layer keeps only the rest."""
        if not self.s.enabled:
            return self.estimate
        _, _, old = self.recent()
        n = min(old.shape[0], new_model_acc.shape[0])
        new_offset = rebase_offset(self._sigma, old[:n], new_model_acc[:n], self.s.max_offset + 5.0)
        self._shift_observer(new_offset - self._sigma)
        self._sigma = new_offset
        if n == self._buf_len:  # later re-bases compare against the model now flying
            self._buf_a[:n] = new_model_acc[:n]
        self.estimate = replace(self.estimate, offset=self._published())
        self._engage(0.0)
        self.rebases += 1
        return self.estimate


__all__ = ["AdaptationEstimate", "AdaptationSettings", "FastAdaptation", "MODES", "applied_estimate", "axis_transfer",
           "dob_step", "engagement", "l1_step", "rebase_offset", "shrink", "sigma_after_transfer", "smooth_step",
           "thrust_transfer"]


def settings_from_controller(ctrl: object) -> AdaptationSettings:
    """``AdaptationSettings`` from ``ControllerConfig`` (``adaptation`` + ``adaptation_settings``)."""
    tuning = getattr(ctrl, "adaptation_settings")
    fields = {f: getattr(tuning, f) for f in AdaptationSettings.__dataclass_fields__ if f != "mode"}
    return AdaptationSettings(mode=getattr(ctrl, "adaptation"), **fields)
