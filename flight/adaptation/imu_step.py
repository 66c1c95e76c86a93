"""A mass step seen in the accelerometer: the thrust effectiveness a sample after it changes.

The accelerometer reads the specific force, which along the body z axis is the acting thrust over the true
mass. Over the acting thrust as the vehicle config's map and mass give it, that is theta = nominal / true
mass (times any error of the thrust map): one direct measurement per log sample (100 Hz), where the mocap
frames show a step only as a bend in the heights, several frames later. Each sample is compared with the
layer's current theta; the deviation's usual offset (an accelerometer's bias, a thrust map's error) and its
noise level (vibration, the motor lag model's misses) are learned in flight, and two successive samples beyond ``ALARM`` standard deviations on the same side (or one far
beyond) raise an alarm. Until the heights can be fitted, the step's theta is the median of the samples since
the onset. Pure arithmetic on a few numbers per sample.
"""

from __future__ import annotations

import math
from collections import deque

WARMUP_SAMPLES = 100  # samples before an alarm may be raised: the noise level is learned first (1 s at 100 Hz)
ALARM = 6.0  # standard deviations two successive samples must exceed, on the same side
ALARM_SINGLE = 12.0  # ... or one sample
NOISE_FLOOR = 0.005  # theta's noise is taken as at least this (0.5 %: a simulated IMU without noise)
POST_SAMPLES = 8  # samples after the onset kept for the step's theta
RECENT_SAMPLES = 16  # samples kept to check a step the frames saw (160 ms)


class ImuStepDetector:
    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._n = 0
        self._bias = 0.0  # mean of sample minus layer: an accelerometer's offset, a thrust map's error
        self._var = 0.0  # variance about it
        self._quiet_t: float | None = None  # the last sample within ALARM
        self._pending: tuple[float, float, float] | None = None  # (t, theta, deviation) of a sample beyond it
        self._post: deque[float] = deque(maxlen=POST_SAMPLES)
        self._onset: float | None = None
        self._recent: deque[tuple[float, float]] = deque(maxlen=RECENT_SAMPLES)  # (t, theta less the offset)
        self.alarms = 0

    @property
    def noise(self) -> float:
        return math.sqrt(max(self._var, NOISE_FLOOR ** 2))

    def sample(self, t: float, theta_meas: float, theta_now: float, stepping: bool) -> float | None:
        """One new sample at ``t``: its theta and the layer's. Returns the onset time when it raises an alarm."""
        if not math.isfinite(theta_meas) or theta_meas <= 0.0:
            return None
        self._recent.append((t, theta_meas - self._bias))
        if stepping:  # a step is being tracked: its samples build its theta, and teach no noise level
            if self._onset is not None and t > self._onset:
                self._post.append(theta_meas - self._bias)
            self._pending = None
            return None
        e = theta_meas - theta_now
        if self._n < WARMUP_SAMPLES:  # learning the noise level: every sample counts
            self._learn(t, e)
            return None
        z = (e - self._bias) / self.noise
        pending = self._pending
        if self._raises(z):
            if abs(z) > ALARM_SINGLE or pending is None:
                first, post = t, [theta_meas - self._bias]
            else:
                first, post = pending[0], [pending[1] - self._bias, theta_meas - self._bias]
            # The step came between the last sample that did not deviate and the first that did.
            onset = first if self._quiet_t is None else 0.5 * (self._quiet_t + first)
            self._onset = onset
            self._post = deque(post, maxlen=POST_SAMPLES)
            self._pending = None
            self.alarms += 1
            return onset
        if abs(z) > ALARM:
            self._pending = (t, theta_meas, z)
            return None
        self._pending = None
        self._learn(t, e)
        return None

    def would_alarm(self, theta_meas: float, theta_now: float) -> bool:
        """Whether ``sample`` would raise an alarm for this sample, no step being tracked. Reads, changes nothing:
        a sample that raises none only teaches the noise level, which can wait."""
        if not math.isfinite(theta_meas) or theta_meas <= 0.0 or self._n < WARMUP_SAMPLES:
            return False
        return self._raises((theta_meas - theta_now - self._bias) / self.noise)

    def _raises(self, z: float) -> bool:
        """A deviation of ``z`` standard deviations raises an alarm: far beyond, or beyond on the pending's side."""
        pending = self._pending
        return abs(z) > ALARM_SINGLE or (abs(z) > ALARM and pending is not None and pending[2] * z > 0.0)

    def _learn(self, t: float, e: float) -> None:
        self._quiet_t = t
        self._n += 1
        k = 1.0 / min(self._n, WARMUP_SAMPLES)
        self._bias += k * (e - self._bias)
        self._var = (1.0 - k) * self._var + k * (e - self._bias) ** 2

    def sees_no_change(self, since: float, theta_before: float) -> bool:
        """Whether the samples since ``since`` show theta where it was (``theta_before``), within 3 standard
        errors: a step the frames' detector fitted from a few frames that the accelerometer does not see.
        False before the noise level is learned or with fewer than 2 samples."""
        if self._n < WARMUP_SAMPLES:
            return False
        after = [x for t, x in self._recent if t > since]
        if len(after) < 2:
            return False
        mean = sum(after) / len(after)
        return abs(mean - theta_before) < 3.0 * self.noise / math.sqrt(len(after))

    def theta(self) -> float | None:
        """The step's theta from the samples since the onset (their median, less the samples' usual offset from
        the layer's theta), None without any."""
        if not self._post:
            return None
        ordered = sorted(self._post)
        mid = len(ordered) // 2
        return ordered[mid] if len(ordered) % 2 else 0.5 * (ordered[mid - 1] + ordered[mid])


__all__ = ["ImuStepDetector"]
