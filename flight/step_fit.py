"""The mass after a detected vertical step, by least squares on the mocap frames around it.

After a step the fast layer's observer has to move the thrust scale while the controller is changing the
thrust to catch the fall: an additive estimate moved into a multiplicative one, around a loop with the
motors' lag and 10 ms between frames. It rang (0.4-0.74 for a true 0.5 on the paper's circle). A step is
instead a change of one number in a known law: the vertical acceleration is theta * a_T - g + r, with a_T
the acting thrust along the body axis over the nominal mass (known, whatever the controller does) and theta
= nominal / true mass. So the heights of the frames around the onset are fitted, in closed form, with

    z(t) = z0 + v0 (t - t0) + known(t) + dtheta * D(t)

where ``known`` is the double integral of the old prediction and D the double integral of a_T from the onset
t0 (zero before it). The frames before the onset pin z0 and v0; every frame after it adds to dtheta. The
onset is searched tick by tick near the detector's run start, the one that fits best. Pure numpy on a ring
of recent ticks; nothing here feeds back, so nothing rings.
"""

from __future__ import annotations

import math

import numpy as np

PRE_FRAMES = 12  # frames before the onset that pin position and velocity (120 ms at 100 Hz)
MIN_POST_FRAMES = 2  # frames after the onset before a fit is tried
MIN_DRIVE = 1e-5  # m: the thrust's double integral since the onset below this cannot tell a mass
SIGNIFICANCE = 4.0  # standard errors a fitted change must exceed; below it the old mass stands (a false alarm
                    # then changes nothing, so the detector can be sensitive)
NOISE_FLOOR = 1e-4  # m: residual noise assumed at least this (mocap sub-mm)


def fit_step(t: np.ndarray, z: np.ndarray, known: np.ndarray, drive: np.ndarray) -> tuple[float, float, float] | None:
    """Least squares of ``z - known = z0 + v0 t + dtheta drive``; returns (dtheta, sum of squared residuals,
    dtheta's standard error)."""
    a = np.column_stack((np.ones_like(t), t, drive))
    y = z - known
    ata = a.T @ a
    if abs(np.linalg.det(ata)) < 1e-18 or float(np.max(np.abs(drive))) < MIN_DRIVE:
        return None
    inv = np.linalg.inv(ata)
    coef = inv @ (a.T @ y)
    res = y - a @ coef
    sse = float(res @ res)
    var = max(sse / max(t.size - 3, 1), NOISE_FLOOR ** 2)
    return float(coef[2]), sse, math.sqrt(var * max(float(inv[2, 2]), 0.0))


class StepFit:
    """Recent ticks and the integrals the fit needs; ``estimate`` fits a step whose onset is near a time."""

    def __init__(self, rate_hz: float, window_s: float = 0.6) -> None:
        self.n = max(8, int(round(window_s * rate_hz)))
        self._t = np.zeros(self.n)
        self._z = np.zeros(self.n)
        self._fresh = np.zeros(self.n, dtype=bool)
        self._pt = np.zeros(self.n)  # double integral of a_T, the acting thrust over the nominal mass
        self._vt = np.zeros(self.n)  # its integral
        self._pr = np.zeros(self.n)  # double integral of the rest of the prediction (-g + model residual)
        self._theta = np.zeros(self.n)  # the layer's 1 / thrust scale at the tick
        self._sigma = np.zeros(self.n)  # the layer's vertical offset at the tick
        self.reset()

    def reset(self) -> None:
        self._i = 0
        self._len = 0
        self._acc: tuple[float, float] | None = None  # (a_T, a_rest) of the last tick, integrated on the next
        self._vt_run = self._pt_run = self._vr_run = self._pr_run = 0.0

    def tick(self, t: float, z: float, a_thrust: float, a_rest: float, theta: float, sigma: float,
             fresh: bool) -> None:
        """One tick: height ``z`` (a fresh frame's when ``fresh``), the acting thrust's acceleration over the
        nominal mass ``a_thrust``, the rest of the predicted vertical acceleration ``a_rest`` (-g + model
        residual), and the layer's current ``theta`` (1 / thrust scale) and vertical offset ``sigma``."""
        if self._acc is not None:  # the previous tick's acceleration acted until now (zero-order hold)
            h = min(max(t - self._t[(self._i - 1) % self.n], 0.0), 0.05)
            a_t, a_r = self._acc
            self._pt_run += h * self._vt_run + 0.5 * h * h * a_t
            self._vt_run += h * a_t
            self._pr_run += h * self._vr_run + 0.5 * h * h * a_r
            self._vr_run += h * a_r
        i = self._i
        self._t[i], self._z[i], self._fresh[i] = t, z, fresh
        self._pt[i], self._vt[i], self._pr[i] = self._pt_run, self._vt_run, self._pr_run
        self._theta[i], self._sigma[i] = theta, sigma
        self._acc = (a_thrust, a_rest)
        self._i = (i + 1) % self.n
        self._len = min(self._len + 1, self.n)

    def estimate(self, onset_hint: float, frame_dt: float) -> tuple[float, float, bool] | None:
        """(theta after the step, the layer's vertical offset at the onset, whether the change is significant)
        from the frames around ``onset_hint``; None if there are too few frames to fit.

        The old law (the layer's theta and offset at the onset) holds before the onset; after it only theta
        differs. Position and velocity at the onset are free, so the frames before it pin them. The onset is
        searched tick by tick near the hint: between two frames, where in the interval the step came matters
        as much as the two frames after it."""
        idx = (self._i - self._len + np.arange(self._len)) % self.n
        t_all = self._t[idx]
        frames = idx[self._fresh[idx]]
        t_frames = self._t[frames]
        best: tuple[float, float, float, float] | None = None
        for j0 in idx[np.abs(t_all - onset_hint) <= 2.0 * frame_dt]:
            t0 = self._t[j0]
            before = np.flatnonzero(t_frames <= t0)
            if before.size < PRE_FRAMES // 2 or t_frames.size - before.size < MIN_POST_FRAMES:
                continue
            use = frames[max(0, before[-1] - PRE_FRAMES + 1):]
            tt = self._t[use] - t0
            theta0, sigma0 = float(self._theta[j0]), float(self._sigma[j0])
            thrust = self._pt[use] - self._pt[j0] - self._vt[j0] * tt  # linear parts are absorbed by z0, v0
            known = theta0 * thrust + (self._pr[use] - self._pr[j0]) + 0.5 * sigma0 * tt * tt
            fitted = fit_step(tt, self._z[use], known, np.where(tt > 0.0, thrust, 0.0))
            if fitted is None:
                continue
            dtheta, score, se = fitted
            if theta0 + dtheta > 0.0 and math.isfinite(dtheta) and (best is None or score < best[2]):
                best = (theta0 + dtheta, sigma0, score, abs(dtheta) / se if se > 0.0 else math.inf)
        if best is None:
            return None
        if best[3] < SIGNIFICANCE:  # no change the frames can tell: the mass before the onset stands
            j = idx[np.argmin(np.abs(t_all - onset_hint))]
            return float(self._theta[j]), float(self._sigma[j]), False
        return best[0], best[1], True


__all__ = ["StepFit", "fit_step"]
