"""A vertical step (a mass change, a payload) seen in the mocap frames, and how long it is tracked.

``FrameStepDetector``: the surprise is the vertical velocity change that the model plus the current estimate
did not predict, summed from one mocap frame to the next (between frames the velocity is a prediction: only
frames carry news). Its noise level is learned in flight, so one threshold holds at 0.3 and at 2 mm of mocap
noise; a CUSUM of the normalised frame surprise raises the alarm: noise averages out, a step adds up.

``StepTracker``: how long an alarm's step is tracked fast. Each alarm holds it for ``step_hold_s``, but never
past ``step_max_s`` after the step's first alarm: while a step is tracked the estimate is pinned to the fit,
so an error the fit does not explain (a vibration, a start-up transient) kept raising alarms that extended
the hold for ever, and the layer missed every later step. After the cap the detector re-arms: the next
alarm starts a new step, with its own onset and fit.
"""

from __future__ import annotations

import math

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


class FrameStepDetector:
    """The frames' CUSUM: ``observe`` each tick; ``run`` says what the alarming side has not explained."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.cusum = (0.0, 0.0)
        self._noise_var = 0.0  # (m/s)^2 per frame: the vertical surprise's noise
        self._v_prev: float | None = None
        self._frames = 0  # mocap frames seen since the reset
        self._frame_surprise = 0.0
        self._t_frame: float | None = None
        self._run = [[0.0, 0.0], [0.0, 0.0]]  # per CUSUM side: summed surprise (m/s) and its span (s)
        self.frame_dt = 0.01  # s between mocap frames, learned

    def forget_velocity(self) -> None:
        """Blind: the next velocity starts a new frame chain."""
        self._v_prev = None

    def observe(self, t: float, v_z: float, a_pred: float, dt: float, fresh: bool) -> bool:
        """One tick's vertical velocity ``v_z`` and predicted acceleration ``a_pred`` (model + estimate).
        True when a frame was scored (the noise level learned): ``cusum`` is then new."""
        v_prev, self._v_prev = self._v_prev, v_z
        if v_prev is None:
            return False
        self._frame_surprise += v_z - v_prev - dt * a_pred
        if not fresh:
            return False
        surprise, self._frame_surprise = self._frame_surprise, 0.0
        # The noise level is learned all the time (a step's few large surprises move it little); alarms wait
        # until it has seen a window of frames.
        self._frames += 1
        k = 1.0 / min(self._frames, NOISE_FRAMES)
        self._noise_var = (1.0 - k) * self._noise_var + k * surprise * surprise
        if self._frames < NOISE_FRAMES:
            return False
        std = math.sqrt(max(self._noise_var, NOISE_FLOOR ** 2))
        before = self.cusum
        self.cusum = cusum_step(self.cusum, surprise / std)
        # What each side's run has not been explained: summed surprise and its duration since that sum left 0.
        span = t - self._t_frame if self._t_frame is not None else 0.0
        for i in (0, 1):
            if before[i] <= 0.0:
                self._run[i] = [0.0, 0.0]
            if self.cusum[i] > 0.0:
                self._run[i][0] += surprise
                self._run[i][1] += span
        if self._t_frame is not None:
            self.frame_dt += 0.05 * (min(t - self._t_frame, 0.1) - self.frame_dt)
        self._t_frame = t
        return True

    def side(self) -> int:
        """The CUSUM side that is higher: 0 upward, 1 downward."""
        return 0 if self.cusum[0] >= self.cusum[1] else 1

    def run(self, side: int) -> tuple[float, float]:
        """(summed surprise m/s, its span s) of ``side``'s current run."""
        dv, span = self._run[side]
        return dv, span

    def clear(self) -> None:
        """An alarm was taken: the sums start over."""
        self.cusum = (0.0, 0.0)
        self._run = [[0.0, 0.0], [0.0, 0.0]]


class StepTracker:
    """Whether a step is being tracked: held ``hold_s`` after each alarm, at most ``max_s`` after its first."""

    def __init__(self, hold_s: float, max_s: float) -> None:
        self.hold_s, self.max_s = hold_s, max_s
        self.reset()

    def reset(self) -> None:
        self.until = -math.inf  # s, the tracking ends here
        self.started = -math.inf  # s, the tracked step's first alarm
        self.threshold_scale = 1.0
        self.last_alarm = -math.inf
        self.capped = 0  # steps whose tracking the cap ended

    def tracking(self, t: float) -> bool:
        return t < self.until

    def tracked_s(self, t: float) -> float:
        """s the current step has been tracked (0 when none is)."""
        return t - self.started if self.tracking(t) else 0.0

    def threshold(self, t: float, base: float) -> float:
        """The alarm level now: ``base`` raised after alarms in a row (see REARM_S)."""
        if t - self.last_alarm > QUIET_RESET_S:
            self.threshold_scale = 1.0
        return base * self.threshold_scale

    def start(self, t: float) -> None:
        """A new step's first alarm (none was tracked, or the last one's cap has passed)."""
        if t - self.until < REARM_S:
            self.threshold_scale = min(2.0 * self.threshold_scale, MAX_THRESHOLD_SCALE)
        self.started = self.last_alarm = t
        self.until = t + min(self.hold_s, self.max_s)

    def restart(self, t: float) -> None:
        """A new onset within the tracking (the accelerometer saw the step): the hold runs from it."""
        if not self.tracking(t):
            self.started = t
        self.last_alarm = t
        self.until = min(t + self.hold_s, self.started + self.max_s)

    def extend(self, t: float) -> None:
        """Another alarm of the same step: held longer, never past the cap."""
        cap = self.started + self.max_s
        if t + self.hold_s > cap and self.until < cap:
            self.capped += 1
        self.until = min(t + self.hold_s, cap)


__all__ = ["FrameStepDetector", "MAX_THRESHOLD_SCALE", "NOISE_FLOOR", "NOISE_FRAMES", "QUIET_RESET_S", "REARM_S",
           "STEP_DRIFT", "StepTracker", "cusum_step"]
