"""Position and velocity from mocap poses: a constant-velocity Kalman filter per axis.

Why a Kalman filter and not finite differences: differencing 100 Hz positions with
0.3 mm noise gives ~40 mm/s velocity noise and half a frame of lag; the filter weighs
each frame by its noise against a white-acceleration motion model, handles dropped
frames and uneven frame spacing through the covariance, and can take the commanded
acceleration as a known input so the 400 Hz prediction between frames does not lag.

The input is the acceleration the vehicle flies, not the one commanded: a tilt takes the attitude
loop's response time to arrive (``attitude_lag``, a first-order lag on x and y; the collective
thrust's motors are an order faster). Predicting with the command itself put the velocity ahead of
the vehicle through every manoeuvre, by the jerk times that lag, and the MPC and the fast layer
flew on that error (measured in docs/history.md#the-estimators-input).

The model is the same on every axis (same noise, same measurement times), so the 2x2
covariance and the gain are scalars shared by the three axes; only the mean is (3,).

Frames arrive in the past (``pose.t`` <= now, plus any ``latency`` the source does not
stamp), so the filter keeps a short history of its predictions since the last frame:
a frame is fused at its own time, and the correction is carried forward exactly (the
model is linear, so a correction (dp, dv) at t_m becomes (dp + dv (t - t_m), dv) at t).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cfknode.flight.latency import CommandDelayPredictor
from cfknode.flight.mellinger import measured_yaw
from cfknode.flight.settings import EstimatorConfig
from cfknode.kernel.imu import ImuSample
from cfknode.mocap.source import Pose

# Velocity uncertainty at the first frame (m/s): the vehicle is on the ground or
# being held, so a metre per second is generous.
_INITIAL_VELOCITY_STD = 1.0
# Predictions kept between frames; 400 Hz ticks and 100 Hz frames use about 5.
_HISTORY = 64


@dataclass(frozen=True)
class StateEstimate:
    """Estimate at time ``t``: position, velocity (world, SI), attitude of the last frame."""

    t: float
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    yaw: float
    # The newest mocap frame as measured (time with the latency taken off, position), unfiltered: the fast
    # layer's step fit reads heights without the filter's lag. None where no frame fed the estimate.
    frame: tuple[float, np.ndarray] | None = None
    # The newest accelerometer sample the vehicle logged (None without one): the fast layer sees a mass change
    # in the specific force a sample after it happens, where the frames need several.
    imu: ImuSample | None = None


class VelocityEstimator:
    def __init__(self, config: EstimatorConfig) -> None:
        if config.process_accel_std <= 0 or config.position_std <= 0:
            raise ValueError("estimator noise levels must be > 0")
        self._q_acc = config.process_accel_std**2
        self._r = config.position_std**2
        self._latency = config.latency
        self._attitude_lag = config.attitude_lag
        self._flown = np.zeros(3)  # the commanded acceleration through the attitude loop's lag (x, y)
        # The command path's delay: ``ahead`` predicts across it (flight/latency.py).
        self.command_path = CommandDelayPredictor(config.command_delay, config.command_delay_z,
                                                  config.command_residual_tau, config.command_lag)
        # History rows 0..n-1: row 0 is the last fused frame (the anchor), later rows
        # the predictions made since. acc[i] is the input over (t[i-1], t[i]].
        self._t = np.zeros(_HISTORY)
        self._p = np.zeros((_HISTORY, 3))
        self._v = np.zeros((_HISTORY, 3))
        self._acc = np.zeros((_HISTORY, 3))
        self._n = 0
        # Shared covariance [[pp, pv], [pv, vv]] at the anchor time.
        self._pp = 0.0
        self._pv = 0.0
        self._vv = 0.0
        self._last_pose_t = -math.inf
        self._quat: np.ndarray | None = None
        self._yaw = 0.0
        self._frame: tuple[float, np.ndarray] | None = None
        self._zero3 = np.zeros(3)

    @property
    def initialized(self) -> bool:
        return self._n > 0

    def reset(self) -> None:
        """Forget everything; the next pose starts the filter again."""
        self._n = 0
        self._last_pose_t = -math.inf
        self._quat = None
        self._flown = np.zeros(3)
        self.command_path.reset()

    def update(self, pose: Pose | None) -> None:
        """Fuse a frame; a frame already seen (same ``t``) or older is ignored."""
        if pose is None or pose.t <= self._last_pose_t:
            return
        self._last_pose_t = pose.t
        self._quat = pose.quaternion
        self._yaw = measured_yaw(pose.quaternion)
        t_m = pose.t - self._latency
        self._frame = (t_m, np.array(pose.position, dtype=float))
        if self._n == 0:
            self._start(t_m, pose.position)
            return

        # Prior mean at t_m from the newest history row at or before it (row 0 if none).
        n = self._n
        ts = self._t
        i = n - 1
        while i > 0 and ts[i] > t_m:
            i -= 1
        h = t_m - ts[i]
        a_seg = self._acc[i + 1] if i + 1 < n else self._acc[i]
        p_prior = self._p[i] + h * self._v[i] + (0.5 * h * h) * a_seg
        v_prior = self._v[i] + h * a_seg

        # Covariance: anchor -> t_m with piecewise-constant white acceleration
        # (Bar-Shalom's DWNA model), then the position measurement.
        dt = t_m - ts[0]
        if dt > 0.0:
            q = self._q_acc
            dt2 = dt * dt
            pp = self._pp + 2.0 * dt * self._pv + dt2 * self._vv + 0.25 * dt2 * dt2 * q
            pv = self._pv + dt * self._vv + 0.5 * dt2 * dt * q
            vv = self._vv + dt2 * q
        else:
            pp, pv, vv = self._pp, self._pv, self._vv
        s = pp + self._r
        k_p = pp / s
        k_v = pv / s
        self._pp = pp * self._r / s
        self._pv = pv * self._r / s
        self._vv = vv - k_v * pv

        resid = pose.position - p_prior
        dp = k_p * resid
        dv = k_v * resid

        # The fused frame becomes the anchor (row 0); later predictions are corrected.
        later = n - (i + 1)  # rows after t_m (the search stops at the last row <= t_m)
        self._acc[0] = a_seg  # before the shift below, which may overwrite the row a_seg views
        if later > 0:
            src = slice(i + 1, n)
            dst = slice(1, 1 + later)
            self._t[dst] = ts[src]
            self._acc[dst] = self._acc[src]
            self._p[dst] = self._p[src] + dp + (self._t[dst, None] - t_m) * dv
            self._v[dst] = self._v[src] + dv
        self._t[0] = t_m
        self._p[0] = p_prior + dp
        self._v[0] = v_prior + dv
        self._n = 1 + later

    def predict(self, now: float, acc: np.ndarray | None = None) -> StateEstimate | None:
        """Estimate at ``now``; ``acc`` is the commanded world acceleration applied since
        the previous call (zero if None), flown through ``attitude_lag``. Returns None before the first pose."""
        n = self._n
        if n == 0:
            return None
        last = n - 1
        h = now - self._t[last]
        if h > 0.0:
            a = self._zero3 if acc is None else np.asarray(acc, dtype=np.float64)
            if self._attitude_lag > 0.0:
                a = self._flown_input(a, h)
            if n == _HISTORY:
                # No frame for a long while: keep the anchor and the newest half.
                keep = _HISTORY // 2
                self._t[1:keep] = self._t[n - keep + 1 : n]
                self._p[1:keep] = self._p[n - keep + 1 : n]
                self._v[1:keep] = self._v[n - keep + 1 : n]
                self._acc[1:keep] = self._acc[n - keep + 1 : n]
                n = keep
                last = n - 1
            p = self._p[last] + h * self._v[last] + (0.5 * h * h) * a
            v = self._v[last] + h * a
            self._t[n] = now
            self._p[n] = p
            self._v[n] = v
            self._acc[n] = a
            self._n = n + 1
        else:
            # Called again at the same time (or the clock stepped back): no new row.
            p = self._p[last].copy()
            v = self._v[last].copy()
        return StateEstimate(t=now, p=p, v=v, q=self._quat, yaw=self._yaw, frame=self._frame)

    def _flown_input(self, acc: np.ndarray, h: float) -> np.ndarray:
        """``acc`` with x and y through the attitude loop's first-order lag over ``h`` s (exact for a held input)."""
        k = -math.expm1(-h / self._attitude_lag)
        self._flown[:2] += k * (acc[:2] - self._flown[:2])
        self._flown[2] = acc[2]
        return self._flown.copy()

    def _start(self, t: float, position: np.ndarray) -> None:
        self._t[0] = t
        self._p[0] = position
        self._v[0] = 0.0
        self._acc[0] = 0.0
        self._pp = self._r
        self._pv = 0.0
        self._vv = _INITIAL_VELOCITY_STD**2
        self._n = 1
