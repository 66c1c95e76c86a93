"""The mass after a detected vertical step, by least squares on the mocap frames around it.

After a step the fast layer's observer has to move the thrust scale while the controller is changing the
thrust to catch the fall: an additive estimate moved into a multiplicative one, around a loop with the
motors' lag and 10 ms between frames. It rang (docs/history.md#the-mass-fitted-at-a-step-and-a-quieter-offset). A step is
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
from dataclasses import dataclass

import numpy as np

PRE_FRAMES = 12  # frames before the onset that pin position and velocity (120 ms at 100 Hz)
MIN_POST_FRAMES = 2  # frames after the onset before a fit is tried
MIN_DRIVE = 1e-5  # m: the thrust's double integral since the onset below this cannot tell a mass
SIGNIFICANCE = 4.0  # standard errors a fitted change must exceed; below it the old mass stands (a false alarm
                    # then changes nothing, so the detector can be sensitive)
NOISE_FLOOR = 1e-4  # m: residual noise assumed at least this (mocap sub-mm)
LAG_MARGIN = 0.25  # another motor lag is taken when its squared residual is below this fraction of the flown one's
LAG_FRAMES = 10  # ... with at least these frames after the onset


@dataclass(frozen=True)
class StepEstimate:
    """What the frames around a detected step tell."""

    theta: float  # 1 / thrust scale after the onset
    sigma: float  # the layer's vertical offset at the onset (it stays)
    significant: bool  # False: no change the frames can tell, theta is the one before the onset
    lag: int  # index of the motor lag whose acting thrust fitted best
    frames: int  # frames after the onset the fit saw


class StepFit:
    """Recent ticks and the integrals the fit needs; ``estimate`` fits a step whose onset is near a time.

    The acting thrust is kept for each candidate motor lag: a step is the strongest excitation the lag ever
    gets (the controller changes the thrust by half the weight), and a wrong lag there biases the mass (a
    150 ms motor fitted as a 15 ms one put the mass of a 0.5x step at the 0.4 floor)."""

    def __init__(self, rate_hz: float, window_s: float = 0.6) -> None:
        self.n = max(8, int(round(window_s * rate_hz)))
        self._t = np.zeros(self.n)
        self._z = np.zeros(self.n)
        self._fresh = np.zeros(self.n, dtype=bool)
        self._a = np.zeros((self.n, 1))  # per lag: a_T, the acting thrust over the nominal mass
        self._ar = np.zeros(self.n)  # the rest of the prediction (-g + model residual)
        self._theta = np.zeros(self.n)  # the layer's 1 / thrust scale at the tick
        self._sigma = np.zeros(self.n)  # the layer's vertical offset at the tick
        self._lag = np.zeros(self.n, dtype=int)  # the lag the layer flew with at the tick
        self.reset()

    def reset(self) -> None:
        self._i = 0
        self._len = 0

    def tick(self, t: float, z: float, a_thrust: float | np.ndarray, a_rest: float, theta: float, sigma: float,
             fresh: bool, lag: int = 0) -> None:
        """One tick: height ``z`` (a fresh frame's when ``fresh``), the acting thrust's acceleration over the
        nominal mass ``a_thrust`` (one per candidate lag, or one value), the rest of the predicted vertical
        acceleration ``a_rest`` (-g + model residual), the layer's current ``theta`` (1 / thrust scale) and
        vertical offset ``sigma``, and the index ``lag`` of the lag the layer flies with. Only stored: the
        integrals are built when a fit needs them (a few frames per step), not on every tick."""
        a_lags = a_thrust if isinstance(a_thrust, np.ndarray) else np.atleast_1d(float(a_thrust))
        if a_lags.size != self._a.shape[1]:  # another set of lags: the ring starts over
            self._a = np.zeros((self.n, a_lags.size))
            self.reset()
        i = self._i
        self._t[i], self._z[i], self._fresh[i], self._ar[i] = t, z, fresh, a_rest
        self._a[i] = a_lags
        self._theta[i], self._sigma[i], self._lag[i] = theta, sigma, lag
        self._i = (i + 1) % self.n
        self._len = min(self._len + 1, self.n)

    def _integrals(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(double integral of a_T per lag, its integral, double integral of the rest) at the ring's ticks ``idx``
        (oldest first), from 0 at the oldest: each tick's acceleration acts until the next (zero-order hold).
        The fit uses differences from the onset with position and velocity free, so where they start is moot."""
        h = np.zeros(idx.size)
        h[1:] = np.clip(np.diff(self._t[idx]), 0.0, 0.05)
        a_t, a_r = self._a[idx][:-1], self._ar[idx][:-1]
        vt = np.zeros((idx.size, a_t.shape[1]))
        vt[1:] = np.cumsum(h[1:, None] * a_t, axis=0)
        pt = np.zeros_like(vt)
        pt[1:] = np.cumsum(h[1:, None] * vt[:-1] + 0.5 * (h[1:] ** 2)[:, None] * a_t, axis=0)
        vr = np.concatenate(([0.0], np.cumsum(h[1:] * a_r)))
        pr = np.concatenate(([0.0], np.cumsum(h[1:] * vr[:-1] + 0.5 * h[1:] ** 2 * a_r)))
        out_pt, out_vt, out_pr = np.zeros((self.n, vt.shape[1])), np.zeros((self.n, vt.shape[1])), np.zeros(self.n)
        out_pt[idx], out_vt[idx], out_pr[idx] = pt, vt, pr
        return out_pt, out_vt, out_pr

    def estimate(self, onset_hint: float, frame_dt: float) -> StepEstimate | None:
        """The step from the frames around ``onset_hint``; None if there are too few frames to fit.

        The old law (the layer's theta and offset at the onset) holds before the onset; after it only theta
        differs. Position and velocity at the onset are free, so the frames before it pin them. The onset is
        searched tick by tick near the hint (between two frames, where in the interval the step came matters
        as much as the two frames after it), and with it the motor lag: every onset and lag is one small
        least squares, solved together."""
        idx = (self._i - self._len + np.arange(self._len)) % self.n
        frames = idx[self._fresh[idx]]
        onsets = idx[np.abs(self._t[idx] - onset_hint) <= 2.0 * frame_dt]
        if frames.size == 0 or onsets.size == 0:
            return None
        t0 = self._t[onsets]
        before = np.searchsorted(self._t[frames], t0, side="right")  # frames at or before each onset
        usable = (before >= PRE_FRAMES // 2) & (frames.size - before >= MIN_POST_FRAMES)
        if not np.any(usable):
            return None
        onsets, t0, before = onsets[usable], t0[usable], before[usable]
        pt_all, vt_all, pr_all = self._integrals(idx)
        w = (np.arange(frames.size)[None, :] >= np.maximum(before - PRE_FRAMES, 0)[:, None]).astype(float)
        tt = self._t[frames][None, :] - t0[:, None]  # (onset, frame)
        theta0, sigma0 = self._theta[onsets], self._sigma[onsets]
        # (onset, frame, lag); the linear parts are absorbed by z0 and v0
        thrust = (pt_all[frames][None, :, :] - pt_all[onsets][:, None, :]
                  - vt_all[onsets][:, None, :] * tt[:, :, None])
        rest = pr_all[frames][None, :] - pr_all[onsets][:, None] + 0.5 * sigma0[:, None] * tt * tt
        y = self._z[frames][None, :, None] - theta0[:, None, None] * thrust - rest[:, :, None]
        drive = np.where(tt[:, :, None] > 0.0, thrust, 0.0)
        ones = np.broadcast_to(np.ones_like(tt)[:, :, None], drive.shape)
        a = np.stack((ones, np.broadcast_to(tt[:, :, None], drive.shape), drive), axis=-1)  # (onset, frame, lag, 3)
        aw = a * w[:, :, None, None]
        ata = np.einsum("jfli,jflk->jlik", aw, a)
        aty = np.einsum("jfli,jfl->jli", aw, y)
        ok = (np.abs(np.linalg.det(ata)) >= 1e-18) & (np.max(np.abs(drive) * w[:, :, None], axis=1) >= MIN_DRIVE)
        ata = np.where(ok[:, :, None, None], ata, np.eye(3))
        inv = np.linalg.inv(ata)
        coef = np.einsum("jlik,jlk->jli", inv, aty)
        res = y - np.einsum("jfli,jli->jfl", a, coef)
        sse = np.einsum("jf,jfl->jl", w, res * res)
        rows = w.sum(axis=1)[:, None]
        var = np.maximum(sse / np.maximum(rows - 3.0, 1.0), NOISE_FLOOR ** 2)
        se = np.sqrt(var * np.maximum(inv[:, :, 2, 2], 0.0))
        dtheta = coef[:, :, 2]
        ok &= np.isfinite(dtheta) & (theta0[:, None] + dtheta > 0.0)
        if not np.any(ok):
            return None
        score = np.where(ok, sse, np.inf)
        flown = int(self._lag[onsets[0]])
        lag = flown if flown < score.shape[1] else 0
        best_by_lag = score.min(axis=0)
        other = int(np.argmin(best_by_lag))
        post = frames.size - before[int(np.argmin(score[:, other]))]
        # Another lag takes over only by a wide margin and after enough frames: in the first ones all lags fit
        # alike, and on a plant flown with its own lag another fitted up to 0.56 of its squares now and then.
        if not math.isfinite(best_by_lag[lag]) or (post >= LAG_FRAMES and best_by_lag[other] < LAG_MARGIN * best_by_lag[lag]):
            lag = other
        j = int(np.argmin(score[:, lag]))
        change = abs(float(dtheta[j, lag])) / float(se[j, lag]) if se[j, lag] > 0.0 else math.inf
        if change < SIGNIFICANCE:  # no change the frames can tell: the mass before the onset stands
            k = idx[np.argmin(np.abs(self._t[idx] - onset_hint))]
            return StepEstimate(float(self._theta[k]), float(self._sigma[k]), False, lag, int(frames.size - before[j]))
        return StepEstimate(float(theta0[j] + dtheta[j, lag]), float(sigma0[j]), True, lag, int(frames.size - before[j]))


__all__ = ["StepEstimate", "StepFit"]
