"""Fast adaptation: what the flying model (nominal, or nominal + KNODE residual) still gets wrong, every tick.

Three estimates, relative to the model's predicted acceleration for the command actually applied:
- ``offset`` d (3, m/s^2): an additive acceleration error, handed to the MPC as a residual constant (integral action);
- ``thrust_scale`` s: mass / nominal mass as the thrust sees it; the Mellinger layer computes thrust with s m;
- ``axis_gain`` k (x, y, 1): how much of a commanded tilt the attitude loop delivers; the Mellinger layer divides by it.
A disturbance estimate sigma comes from an observer on velocity (no differentiation of v), whose input is the thrust
actually sent along the *measured* body axis (fed the commanded acceleration instead, the 2 Hz observer and the MPC
oscillated through the attitude loop's lag). Its vertical part is moved into s, shifting sigma so that model + layer
predicts the same acceleration before and after; what remains is d. k compares the horizontal acceleration the
measured attitude gives with the one commanded. "dob" (a first-order disturbance observer) is the method; "l1"
(velocity predictor, adaptive law, output filter) stays for comparison: its filters add lag for no gain on a step.

No single bandwidth serves both a noisy mocap and a payload step, so the observer is slow between steps and
a step detector raises an alarm: a CUSUM of the frame-to-frame vertical velocity surprise, normalised by its
noise level learned in flight. For ``step_hold_s`` after it the mass is fitted to the mocap heights around
the onset (step_fit.py), which does not ring as moving an additive estimate into the mass did; a fit that
sees no step keeps the mass. A step is tracked at most ``step_max_s``. Without heights the observer runs at
``step_bandwidth_hz`` instead, with the run's unexplained acceleration added at the alarm. Passing under another
drone's wake no heavier step is called (wake_guard.py).

What the MPC gets is not sigma itself, which passes the velocity estimate's noise straight through at gain omega:
it is sigma behind a second low-pass pole (``output_bandwidth``; bypassed vertically while a step is tracked), and
horizontally shrunk where it is not clearly above ``offset_deadband`` (what is left at the circle's frequency
follows the attitude measurement's age and the attitude loop, which the MPC cannot cancel as a constant). The
thrust scale learns from the smoothed vertical estimate too.

What the controller flies with is ``applied``: the estimate on the axes where it acts, the model alone on the
others (``engagement``). An axis acts once the error the layer sees there (its offset; vertically the offset plus
the mass estimate's share at hover) is above ``engage_level``, or its slow mean above ``engage_slow_level``, and
lets go after ``release_s`` with both under half their levels. On a plant the model matches the estimate is
noise, and such a flight is plain MPC's; a step, a wind or a thrust-map error is far above the level within a
fraction of a second. The measurements behind each choice: docs/results.md#fast-adaptation and
docs/history.md#fast-adaptation-a-slow-observer-a-step-detector-the-motor-lag-chosen-in-flight.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import NamedTuple, Sequence

import numpy as np

from cfknode.flight.adaptation.engagement import Engagement
from cfknode.flight.adaptation.estimate import AdaptationEstimate, applied_estimate
from cfknode.flight.adaptation.imu_step import ImuStepDetector
from cfknode.flight.adaptation.recent import Recent, RecentTicks
from cfknode.flight.adaptation.observer import (
    L1Gains, axis_transfer, dob_step_floats, l1_step, rebase_offset, shrink, sigma_after_transfer_floats,
    smooth_step_floats, thrust_transfer,
)
from cfknode.flight.adaptation.settings import MODES, AdaptationSettings
from cfknode.flight.adaptation.step_detect import FrameStepDetector, StepTracker
from cfknode.flight.adaptation.step_fit import LAG_FRAMES, StepFit
from cfknode.flight.adaptation.wake_guard import WakeGuard


class LoopExtras(NamedTuple):
    """What the adaptation loop adds to a tick beyond the measurements (see ``FastAdaptation.update``). A named
    tuple: built every tick, where a frozen dataclass's constructor cost a few microseconds."""

    u_commanded: np.ndarray | None = None
    thrust_by_lag: np.ndarray | None = None
    lag: int = 0
    imu_theta: tuple[float, float] | None = None
    accel_part: np.ndarray | None = None
    neighbour: np.ndarray | None = None  # the drone above where the flying model saw it (recent.py)
    above: np.ndarray | None = None  # the drone above now, for the wake guard (the fleet's, or ``neighbour``)


_NO_EXTRAS = LoopExtras()
_NO_PART = np.zeros(3)  # the fast part inside the offset when there is none: shared, so read-only
_NO_PART.flags.writeable = False


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
        self._recent = RecentTicks(max(1, int(round(settings.rebase_window_s * rate_hz))))
        self.resets = 0
        self.rebases = 0
        self.steps = 0  # vertical steps detected
        self.fits = 0  # frames at which a step's mass was re-fitted
        self.imu_steps = 0  # steps the accelerometer raised first
        self._fit = StepFit(rate_hz)
        self._imu = ImuStepDetector()
        self._frames = FrameStepDetector()
        self.tracker = StepTracker(settings.step_hold_s, settings.step_max_s)
        self.wake = WakeGuard(settings.wake_radius)  # ``extras.above``: no heavier step passing under its wake
        self._engagement = Engagement(settings.engage_level, settings.engage_slow_level, settings.engage_slow_s,
                                      settings.release_s)
        self.reset()

    @property
    def acts(self) -> np.ndarray:
        """x, y, vertical: the axes the estimate acts on (see engagement.py)."""
        return np.array(self._engagement.acts)

    def reset(self) -> None:
        """Back to the model alone (take-off, landing, non-finite input)."""
        self.estimate = AdaptationEstimate.neutral()
        self._engagement.reset()
        self.applied = applied_estimate(self.estimate, self._engagement.acts)  # what the controller flies with
        self._sigma = np.zeros(3)
        self._out = np.zeros(3)  # the published offset before its bound and the saturation hold
        self._obs: np.ndarray | None = None  # dob z or l1 v_hat; None: re-synchronise on the next update
        self._sigma_hat = np.zeros(3)
        self._last_fresh_t = -math.inf
        self._t_prev: float | None = None
        self._recent.reset()
        self._frames.reset()
        self.tracker.reset()
        self.wake.reset()
        self._omega_z = float(self.omega[2])  # the vertical bandwidth the observer's state is scaled for
        self._jump = 0.0  # m/s^2 added to the vertical estimate at an alarm
        self._fit.reset()
        self._onset_hint: float | None = None  # s, the frame before the alarm's run began
        self._fitted: tuple[float, float, bool] | None = None  # (thrust scale, vertical offset, significant)
        self._fitting = False  # heights are given: steps are fitted
        self.fit_lag: tuple[int, float] | None = None  # the last significant fit's (``thrust_by_lag`` index, onset s)
        self._imu.reset()
        self._imu_step = False  # the step being tracked was raised by the accelerometer
        self._imu_sigma = 0.0  # the vertical offset when it was
        self._fit_frames = 0  # frames after the onset in the step's latest height fit
        self._theta_at_alarm = 1.0  # 1 / thrust scale when the frames' detector raised its alarm
        self._vetoed = False  # the accelerometer saw no step in this hold of the frames' detector
        self._accel_part: np.ndarray | None = None  # the accelerometer's fast part this tick (accel_path.py)
        self._accel_applied = np.zeros(3)  # the fast part inside the published offset
        self.resets += 1

    def update(
        self, t: float, v_meas: np.ndarray, x_meas: np.ndarray | None, u_applied: np.ndarray, model_acc: np.ndarray,
        saturated: tuple[bool, bool] = (False, False), pose_fresh: bool = True, extras: LoopExtras = _NO_EXTRAS,
    ) -> AdaptationEstimate:
        """One tick. ``u_applied`` / ``model_acc`` are the previous tick's command as the vehicle flew it (sent
        thrust along the measured body axis, in the model's input space) and the model's acceleration for it;
        ``saturated`` is (thrust at the clamp, tilt limited) for that command. ``extras`` (``LoopExtras``):
        ``u_commanded`` is what the Mellinger layer was asked for (after its limits), for the axis gains. ``thrust_by_lag``: the acting
        thrust's vertical acceleration over the nominal mass under each candidate motor lag, ``lag`` the one
        ``u_applied`` used (a step's fit then tells the lag too: ``fit_lag``). ``imu_theta``: (time, theta) of an
        accelerometer sample new this tick, its specific force over the acting thrust's per nominal mass
        (imu_step.py). ``accel_part``: what the accelerometer's fast path adds to the offset this tick
        (accel_path.py), None without it. Returns the estimate for this tick."""
        u_commanded, thrust_by_lag = extras.u_commanded, extras.thrust_by_lag
        lag, imu_theta = extras.lag, extras.imu_theta
        self._accel_part = extras.accel_part
        if not self.s.enabled:
            return self.estimate
        if not finite_sum(v_meas, u_applied, model_acc):  # one check: nan, inf (on floats: see finite_sum)
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
            self._frames.forget_velocity()
            self._fit.reset()
            # Frozen: the slow estimate is held, but a fast part is only right for the moment it was measured.
            held = self.estimate.offset - self._accel_applied
            self._accel_applied = np.zeros(3)
            self.estimate = replace(self.estimate, offset=held, frozen=True, saturated=thrust_sat or tilt_sat)
            self.applied = applied_estimate(self.estimate, self._engagement.acts)
            return self.estimate

        self._fitting = self.s.mode == "dob" and self.s.step_threshold > 0.0 and x_meas is not None
        if self._fitting:
            scale = self.estimate.thrust_scale  # u_applied's thrust was divided by it: a_T is what the motors did
            u_z, a_z = u_applied.item(2), model_acc.item(2)  # floats: numpy scalars cost ~0.1 us an operation
            a_thrust = (u_z + self.g) * scale if thrust_by_lag is None else thrust_by_lag
            self._fit.tick(t, x_meas.item(2), a_thrust, (a_z - u_z) - self.g, 1.0 / scale, self._out.item(2),
                           pose_fresh, lag)
        under_wake = self.wake.update(t, None if x_meas is None else x_meas[0:3], extras.above)
        if self._fitting and imu_theta is not None and not (
                under_wake and imu_theta[1] > 1.0 / self.estimate.thrust_scale):  # heavier, in a pass: the wake
            self._imu_sample(t, *imu_theta)
        stepping = self._detect_step(t, v_meas.item(2), model_acc.item(2), dt, thrust_sat, pose_fresh, under_wake)
        fit = self._refit(stepping, pose_fresh)
        if fit is not None:
            self._jump = 0.0  # the fit tells whether there was a step; the run's mean acceleration is not added
        omega = self._observe(v_meas, model_acc, dt, stepping)
        fitted_scale = None
        if fit is not None:  # the fitted mass, or the one before the onset if the frames show no step; either
            fitted_scale = fit[0]  # way the vertical offset stays what it was before the onset
            self._sigma[2] = self._out[2] = fit[1]
            if self.s.mode == "dob":
                self._obs[2] = v_meas[2] - fit[1] / omega[2]
        self._settle(u_applied, u_commanded, thrust_sat, tilt_sat, dt, stepping, omega, fitted_scale)
        self._recent.add(x_meas if x_meas is not None else np.concatenate((np.zeros(3), v_meas)), u_applied, model_acc,
                         extras.neighbour)
        return self.estimate

    def _observe(self, v_meas: np.ndarray, model_acc: np.ndarray, dt: float, stepping: bool) -> np.ndarray:
        """The observer's tick (at the step bandwidth vertically while a step is tracked), bounded, and the
        published offset's low-pass. Returns the bandwidths it ran at."""
        omega = self.omega if not stepping else np.array([self.omega[0], self.omega[1], self.omega_step])
        if self.s.mode == "dob":
            if omega[2] != self._omega_z or self._jump:  # switch: rescale so that sigma continues (+ the jump)
                self._sigma = self._sigma.copy()
                self._sigma[2] = float(np.clip(self._sigma[2] + self._jump, -self.s.max_offset, self.s.max_offset))
                self._jump = 0.0
                self._obs = self._obs.copy()
                self._obs[2] = v_meas[2] - self._sigma[2] / omega[2]
                self._omega_z = float(omega[2])
            z, sigma = dob_step_floats(self._obs.tolist(), v_meas.tolist(), model_acc.tolist(), omega.tolist(), dt)
            self._obs = np.array(z)
        else:
            gains = L1Gains(self.s.predictor_gain, self.s.adaptation_gain, self.s.max_offset + 5.0)
            self._obs, self._sigma_hat, new_sigma = l1_step(
                self._obs, self._sigma_hat, self._sigma, v_meas, model_acc, gains, self.omega, dt)
            sigma = new_sigma.tolist()
        # Anti-windup, first half: the observer is fed the command as flown (clamped thrust, limited tilt), so
        # the gap between what was asked and what the limits let through is never integrated as a disturbance.
        # Projection: the estimate stays in its box (the observer is told, so it does not wind up beyond it).
        m = self.s.max_offset
        bounded = np.array(sigma)
        if not all(-m <= x <= m for x in sigma):  # floats: cheaper than numpy on three numbers
            unbounded, bounded = bounded, np.clip(bounded, -m, m)
            self._shift_observer(bounded - unbounded, omega)
        self._sigma = bounded
        if self.s.mode == "dob":  # a tracked step is published as fast as the observer learns it
            omega_out = self._omega_out_step if stepping else self.omega_out
            self._out = np.array(smooth_step_floats(self._out.tolist(), bounded.tolist(), omega_out.tolist(), dt))
        else:
            self._out = bounded
        return omega

    @property
    def sigma(self) -> np.ndarray:
        """The observer's estimate (m/s^2, before the output filter): what the flying prediction leaves."""
        return self._sigma

    def reexpress(self, d_sigma: np.ndarray) -> None:
        """The flying prediction moved by -``d_sigma`` (the model's coefficients, composite.py): the observer
        and the offset take it, so that prediction + layer continues. Bounded as the observer is."""
        if self._obs is None or not any(d_sigma.tolist()):
            return
        m = self.s.max_offset
        moved = np.clip(self._sigma + d_sigma, -m, m)
        self._shift_observer(moved - self._sigma, self.omega)
        self._sigma = moved

    def stalled(self, t: float) -> bool:
        """Whether the layer's last tick is longer ago than a stale pose (a stalled host): a blind spell too. The drone
        moved meanwhile, and integrating across the gap read that motion as a disturbance (+-6 m/s^2 after 0.59 s)."""
        return self._t_prev is not None and t - self._t_prev > self.s.stale_pose_s

    def _detect_step(self, t: float, v_z: float, a_z: float, dt: float, thrust_sat: bool, fresh: bool,
                     under_wake: bool = False) -> bool:
        """True while a vertical step (a mass, a payload) is tracked fast (step_detect.py); none heavier in a pass."""
        if self.s.step_threshold <= 0.0 or self.s.mode != "dob":
            return False
        tracker, frames = self.tracker, self._frames
        stepping = tracker.tracking(t)
        if not frames.observe(t, v_z, a_z + float(self._sigma[2]), dt, fresh):
            return stepping
        side = frames.side()
        if under_wake and side == 1:  # downward: the wake's surprise, not a heavier vehicle
            frames.clear()
            return stepping
        if frames.cusum[side] > tracker.threshold(t, self.s.step_threshold) and not thrust_sat:
            if not stepping:
                dv, span = frames.run(side)
                if span > 0.0:  # the run's mean unexplained acceleration joins the estimate at once
                    self._jump = dv / span
                tracker.start(t)
                self._start_step(t, t - span, by_imu=False)
                self.steps += 1
            elif not self._vetoed:
                tracker.extend(t)
            frames.clear()
            return True
        return stepping

    def needs_sample(self, t: float, theta: float) -> bool:
        """Whether an accelerometer sample of ``theta`` (``LoopExtras.imu_theta``) changes this tick's estimate: a
        step is tracked (its samples set the mass), or the sample raises a step's alarm. Reads, changes nothing."""
        if not (self.s.enabled and self.s.mode == "dob" and self.s.step_threshold > 0.0):
            return False
        return self.tracker.tracking(t) or self._imu.would_alarm(theta, 1.0 / self.estimate.thrust_scale)

    def _imu_sample(self, t: float, t_sample: float, theta: float) -> None:
        """An accelerometer sample: a step it sees starts the step's tracking at once, from its onset. A hold the
        frames' detector raised does not stop it: that alarm can be a false one just before a real step (a
        0.5x step 76 ms after one went unseen, and the fit searched for its onset at the false alarm's)."""
        tracking = self.tracker.tracking(t)
        onset = self._imu.sample(t_sample, theta, 1.0 / self.estimate.thrust_scale, tracking and self._imu_step)
        if onset is None:
            return
        self.steps += int(not tracking)  # within a hold of the frames' detector: the same step, now seen
        self.imu_steps += 1
        self.tracker.restart(t)
        self._start_step(t, onset, by_imu=True)
        self._frames.clear()
        self._fitted = None  # a fit around another onset says nothing about this one

    def _start_step(self, t: float, onset: float, by_imu: bool) -> None:
        """What either detector's alarm sets: the onset the fit searches near, and what the hold starts from."""
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
            got = self._fit.estimate(self._onset_hint, self._frames.frame_dt)
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
                self.fit_lag = (got.lag, self._onset_hint) if got.significant else None
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
        scale, gain = est.thrust_scale, est.axis_gain
        sigma = self._sigma
        # Moving held error into s is no integration: it changes no prediction (see sigma_after_transfer).
        rate = s.step_thrust_rate if stepping else s.thrust_rate
        if fitted_scale is not None:  # a fitted step sets the scale; sigma was pinned by the caller
            new_scale = scale = fitted_scale
        else:
            new_scale = thrust_transfer(float(self._out[2]), float(u[2]), self.g, scale, rate, dt,
                                        s.thrust_scale_bounds)
        new_gain = gain  # shared, never written: a new array when the gains move
        if u_cmd is not None and not tilt_sat and s.axis_rate > 0.0:
            # delivered / commanded horizontal acceleration: the attitude loop's effectiveness (floats: numpy's
            # scalars cost ~0.1 us an operation)
            (ux, uy, _), (cx, cy), (kx, ky, kz) = u.tolist(), (float(u_cmd[0]), float(u_cmd[1])), gain.tolist()
            new_gain = np.array([axis_transfer(ux - cx, cx, kx, s.axis_rate, dt, s.axis_gain_bounds),
                                 axis_transfer(uy - cy, cy, ky, s.axis_rate, dt, s.axis_gain_bounds), kz])
        if new_scale != scale:
            moved = sigma_after_transfer_floats(sigma.tolist(), u.tolist(), self.g, scale, new_scale)
            self._shift_observer([m - x for m, x in zip(moved, sigma.tolist())], omega)
            self._sigma = np.array(moved)
        bounded = self._bounded_out()
        offset = self._with_fast_part(self._published(bounded), stepping)
        # Second half: on a saturated axis the MPC's offset is held; a growing one would only push the plan
        # further into a limit it cannot act beyond (the mass estimate keeps learning from the flown thrust).
        if tilt_sat or thrust_sat:
            offset = np.where(np.array([tilt_sat, tilt_sat, thrust_sat]), est.offset, offset)
        self.estimate = AdaptationEstimate(offset, new_scale, new_gain, frozen=False, saturated=thrust_sat or tilt_sat,
                                           stepping=stepping)
        self._engage(dt, bounded)

    def _engage(self, dt: float, bounded: tuple[float, float, float] | None = None) -> None:
        """Which axes act, from the evidence: the horizontal offsets before their shrink, and vertically the offset
        plus what the mass estimate moved out of it (its error at hover). ``bounded``: ``_bounded_out()`` if known."""
        x, y, z = self._bounded_out() if bounded is None else bounded
        acts = self._engagement.update((x, y, z + (self.estimate.thrust_scale - 1.0) * self.g), dt)
        self.applied = applied_estimate(self.estimate, acts)

    def _with_fast_part(self, offset: np.ndarray, stepping: bool) -> np.ndarray:
        """The published offset plus the accelerometer's fast part, bounded. Not vertically while a step is
        tracked: the step's fit sets the vertical estimate then, and the part would count the step twice."""
        part = self._accel_part
        if part is None:
            self._accel_applied = _NO_PART
            return offset
        if stepping:
            part = np.array([part[0], part[1], 0.0])
        m = self.s.max_offset
        total = np.clip(offset + part, -m, m)
        self._accel_applied = total - offset
        return total

    def _published(self, bounded: tuple[float, float, float] | None = None) -> np.ndarray:
        """The offset the MPC gets: bounded, the horizontal part shrunk (the vertical one is kept small by the
        thrust-scale transfer; a shrink there would lag a ramp such as a battery's sag). ``bounded``: as _engage."""
        x, y, z = self._bounded_out() if bounded is None else bounded
        band = self.s.offset_deadband
        return np.array([shrink(x, band), shrink(y, band), z])

    def _bounded_out(self) -> tuple[float, float, float]:
        """The offset before its shrink, bounded (floats: numpy's per-call cost on three numbers is the work)."""
        m = self.s.max_offset
        x, y, z = self._out.tolist()
        return min(max(x, -m), m), min(max(y, -m), m), min(max(z, -m), m)

    def _shift_observer(self, d_sigma: np.ndarray | Sequence[float], omega: np.ndarray | None = None) -> None:
        """Make the observer report sigma + d_sigma from now on (its prediction continues from there); the
        published offset moves with it (a re-expression, not news). Floats: the same numbers as the arrays'."""
        d = d_sigma.tolist() if isinstance(d_sigma, np.ndarray) else d_sigma
        self._out = np.array([o + x for o, x in zip(self._out.tolist(), d)])
        if self._obs is None:
            return
        if self.s.mode == "dob":
            w = (self.omega if omega is None else omega).tolist()
            self._obs = np.array([z - x / wi for z, x, wi in zip(self._obs.tolist(), d, w)])
        else:
            self._sigma_hat = np.array([h + x for h, x in zip(self._sigma_hat.tolist(), d)])

    def _sync(self, v: np.ndarray) -> None:
        if self.s.mode == "dob":
            self._obs = v - self._sigma / self.omega
            self._omega_z = float(self.omega[2])
        else:
            self._obs = v.copy()
            self._sigma_hat = self._sigma.copy()

    def recent(self) -> Recent:
        """The buffered recent ticks (recent.py): states, commands, the flying model's accelerations, neighbours."""
        return self._recent.view()

    def rebase(self, new_model_acc: np.ndarray) -> AdaptationEstimate:
        """A model swap: ``new_model_acc`` (n, 3) is the NEW model's acceleration on ``recent()``'s ticks.

        The offset absorbs the difference so model + layer is continuous; the learner's model takes over what it
        explains and the layer keeps only the rest."""
        if not self.s.enabled:
            return self.estimate
        old = self.recent().a
        n = min(old.shape[0], new_model_acc.shape[0])
        new_offset = rebase_offset(self._sigma, old[:n], new_model_acc[:n], self.s.max_offset + 5.0)
        self._shift_observer(new_offset - self._sigma)
        self._sigma = new_offset
        if n == len(self._recent):  # later re-bases compare against the model now flying
            self._recent.set_accelerations(new_model_acc[:n])
        self.estimate = replace(self.estimate, offset=self._published())
        self._engage(0.0)
        self.rebases += 1
        return self.estimate


def finite_sum(*vectors: np.ndarray) -> bool:
    """Whether the 3-vectors' summed elements are finite (a NaN or inf anywhere makes the sum so): the number
    ``float(v1.sum() + v2.sum() + ...)`` is, added in its order with floats (numpy's reduction: ~1 us a vector)."""
    total = 0.0
    for i, v in enumerate(vectors):
        a0, a1, a2 = v.tolist()
        part = (a0 + a1) + a2
        total = part if i == 0 else total + part
    return math.isfinite(total)


__all__ = ["FastAdaptation", "LoopExtras", "finite_sum"]
