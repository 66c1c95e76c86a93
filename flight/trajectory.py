"""Reference trajectories: take off, settle, fly a pattern, settle, land.

The reference is a sum of three smooth terms, each constant outside its own time window:

    p(t) = start + takeoff(t) + pattern(t) + landing(t)

- takeoff: quintic "smootherstep" from the start position to the pattern's first point;
- pattern: the shape (circle, figure-8; nothing for hover) at phase theta(t), minus its
  first point, so it is zero before the pattern and the final offset after it;
- landing: quintic descent from the pattern's last point to z = 0.

The quintic has zero first and second derivatives at both ends, so clipping its
argument to [0, 1] makes every term C2 with no masks, and the phase rate ramps in and
out with the same quintic, so velocity and acceleration stay continuous (C1 phase rate).
Every derivative is analytic, and ``sample`` evaluates only the terms whose window the
requested times touch (the common tick, inside the pattern at full speed, is a few
trigonometric calls).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import MappingProxyType
from typing import Mapping, Sequence

import numpy as np

from cfknode.flight.settings import TrajectoryConfig
from cfknode.kernel.reference import RefSamples


def _smootherstep(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """s = 10 tau^3 - 15 tau^4 + 6 tau^5 and its first two derivatives in tau."""
    t2 = tau * tau
    one_minus = 1.0 - tau
    s = t2 * tau * (10.0 + tau * (6.0 * tau - 15.0))
    ds = 30.0 * t2 * one_minus * one_minus
    dds = 60.0 * tau * one_minus * (1.0 - 2.0 * tau)
    return s, ds, dds


def _smootherstep_integral(tau: np.ndarray) -> np.ndarray:
    """Integral of the smootherstep from 0 to tau (equals 1/2 at tau = 1)."""
    t2 = tau * tau
    return t2 * t2 * (2.5 + tau * (tau - 3.0))


def _clip(x: np.ndarray, low: float, high: float) -> np.ndarray:
    # np.clip's Python wrapper costs twice as much on the 21-element arrays of a tick.
    return np.minimum(np.maximum(x, low), high)


def _ramp_terms(
    t: np.ndarray, lo: float, hi: float, t0: float, ramp: float
) -> tuple[np.ndarray | float, np.ndarray | float, np.ndarray | float]:
    """Integral, value and slope of a smootherstep rate ramp from 0 (at t0) to 1 (at t0 + ramp)."""
    if hi <= t0:
        return 0.0, 0.0, 0.0
    if lo >= t0 + ramp:
        return t - (t0 + 0.5 * ramp), 1.0, 0.0
    x = t - t0
    tau = _clip(x * (1.0 / ramp), 0.0, 1.0)
    s, ds, _ = _smootherstep(tau)
    integral = ramp * _smootherstep_integral(tau) + np.maximum(x - ramp, 0.0)
    return integral, s, ds * (1.0 / ramp)


class Trajectory:
    """A full flight reference; build it with ``make_trajectory``."""

    def __init__(self, cfg: TrajectoryConfig, start_position: Sequence[float]) -> None:
        start = np.asarray(start_position, dtype=np.float64).reshape(3)
        self.kind = cfg.kind
        cx, cy = cfg.center
        h = cfg.height
        if cfg.kind == "circle":
            self._omega = cfg.speed / cfg.radius
            first = np.array([cx + cfg.radius, cy, h])
        elif cfg.kind == "figure8":
            # Gerono lemniscate x = R sin(th), y = R/2 sin(2 th): speed R w sqrt(cos^2 th + cos^2 2th)
            # peaks at the centre crossing, R w sqrt(2), which is set to ``speed``.
            self._omega = cfg.speed / (cfg.radius * math.sqrt(2.0))
            first = np.array([cx, cy, h])
        elif cfg.kind in ("line", "vertical"):
            # A back-and-forth along x (line) or z (vertical): offset R sin(th), so the speed
            # R w peaks at the centre, where a line's passes are timed (th = k pi), and is ``speed``.
            self._omega = cfg.speed / cfg.radius
            first = np.array([cx, cy, h])
        elif cfg.kind == "hover":
            self._omega = 0.0
            first = np.array([cx, cy, h])
        else:
            raise ValueError(f"unknown trajectory kind {cfg.kind!r}")
        self._radius = cfg.radius
        if cfg.settle_duration < 0 or cfg.ramp_duration < 0:
            raise ValueError("trajectory settle_duration and ramp_duration must be >= 0")

        d_pat = cfg.duration
        ramp = min(cfg.ramp_duration, 0.5 * d_pat) if cfg.kind != "hover" else 0.0
        t_to = cfg.takeoff_duration
        t_p0 = t_to + cfg.settle_duration
        t_p1 = t_p0 + d_pat
        t_l0 = t_p1 + cfg.settle_duration
        t_l1 = t_l0 + cfg.land_duration
        self._t_to = t_to
        self._t_p0, self._t_p1, self._ramp = t_p0, t_p1, ramp
        self._t_l0, self._land = t_l0, cfg.land_duration
        # Phase at the end of the ramp-in (w ramp / 2) and at the end of the pattern.
        self._theta_full0 = 0.5 * self._omega * ramp
        self._theta_end = self._omega * (d_pat - ramp)

        self._start = start
        self._first = first
        self._takeoff_disp = first - start
        self._pattern_end_offset = self._offset_const(self._theta_end)
        last = first + self._pattern_end_offset
        self._land_disp = np.array([0.0, 0.0, -last[2]])
        self._final = last + self._land_disp
        self._segments: Mapping[str, tuple[float, float]] = MappingProxyType(
            {
                "takeoff": (0.0, t_to),
                "settle_start": (t_to, t_p0),
                "pattern": (t_p0, t_p1),
                "settle_end": (t_p1, t_l0),
                "land": (t_l0, t_l1),
            }
        )
        self._duration = t_l1

    @property
    def duration(self) -> float:
        """End of the landing, s; ``sample`` holds the final point after it."""
        return self._duration

    @property
    def segments(self) -> Mapping[str, tuple[float, float]]:
        """Ordered name -> (t0, t1): takeoff, settle_start, pattern, settle_end, land."""
        return self._segments

    @property
    def pattern_window(self) -> tuple[float, float]:
        return self._segments["pattern"]

    def phase_times(self, phase: float) -> np.ndarray:
        """Flight times in the pattern at which the phase theta is a multiple of ``phase`` (0 excluded):
        a line's centre crossings for ``phase`` = pi. Found on the phase at 1 ms resolution, then refined
        linearly, so ramps are honoured."""
        t0, t1 = self.pattern_window
        if self._omega == 0.0 or t1 <= t0:
            return np.zeros(0)
        t = np.arange(t0, t1, 1e-3)
        theta, _, _ = self._phase(t, t0, t1)
        k = np.floor(np.asarray(theta) / phase + 1e-12)
        idx = np.flatnonzero(np.diff(k) > 0)
        th = np.asarray(theta)
        frac = ((k[idx + 1] * phase) - th[idx]) / np.maximum(th[idx + 1] - th[idx], 1e-15)
        return t[idx] + frac * (t[idx + 1] - t[idx])

    @property
    def final_position(self) -> np.ndarray:
        return self._final.copy()

    def sample(self, t: np.ndarray) -> RefSamples:
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        n = t.shape[0]
        lo = float(t.min())
        hi = float(t.max())
        const = self._start.copy()  # the sum of the terms that are constant over [lo, hi]
        p = np.zeros((n, 3))
        v = np.zeros((n, 3))
        a = np.zeros((n, 3))

        # Takeoff term.
        if hi <= 0.0:
            pass
        elif lo >= self._t_to:
            const += self._takeoff_disp
        else:
            self._add_step(t, 0.0, self._t_to, self._takeoff_disp, p, v, a)

        # Pattern term.
        if self._omega == 0.0 or hi <= self._t_p0:
            pass
        elif lo >= self._t_p1:
            const += self._pattern_end_offset
        else:
            self._add_pattern(t, lo, hi, p, v, a)

        # Landing term.
        if hi <= self._t_l0:
            pass
        elif lo >= self._t_l0 + self._land:
            const += self._land_disp
        else:
            self._add_step(t, self._t_l0, self._land, self._land_disp, p, v, a)

        p += const
        return RefSamples(t=t, p=p, v=v, a=a, yaw=np.zeros(n))

    @staticmethod
    def _add_step(
        t: np.ndarray, t0: float, duration: float, disp: np.ndarray, p: np.ndarray, v: np.ndarray, a: np.ndarray
    ) -> None:
        tau = _clip((t - t0) * (1.0 / duration), 0.0, 1.0)
        s, ds, dds = _smootherstep(tau)
        p += s[:, None] * disp
        v += (ds * (1.0 / duration))[:, None] * disp
        a += (dds * (1.0 / (duration * duration)))[:, None] * disp

    def _phase(self, t: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray | float, np.ndarray | float]:
        """theta, theta', theta'' of the pattern at times t (some of them in the pattern window)."""
        w, ramp, t_p0, t_p1 = self._omega, self._ramp, self._t_p0, self._t_p1
        if lo >= t_p0 + ramp and hi <= t_p1 - ramp:
            # Full speed over the whole request: the common 400 Hz case.
            return w * (t - (t_p0 + ramp)) + self._theta_full0, w, 0.0
        if ramp == 0.0:
            inside = (t >= t_p0) & (t < t_p1)
            return w * _clip(t - t_p0, 0.0, t_p1 - t_p0), w * inside, 0.0
        # Phase rate w * (ramp_in(t) - ramp_out(t)), each a smootherstep over ``ramp``
        # seconds; the phase integrates each ramp, continued linearly past its end.
        th_in, rate_in, acc_in = _ramp_terms(t, lo, hi, t_p0, ramp)
        th_out, rate_out, acc_out = _ramp_terms(t, lo, hi, t_p1 - ramp, ramp)
        return w * (th_in - th_out), w * (rate_in - rate_out), w * (acc_in - acc_out)

    def _add_pattern(self, t: np.ndarray, lo: float, hi: float, p: np.ndarray, v: np.ndarray, a: np.ndarray) -> None:
        theta, th_d, th_dd = self._phase(t, lo, hi)
        r = self._radius
        c = np.cos(theta)
        s = np.sin(theta)
        if self.kind in ("line", "vertical"):
            k = 0 if self.kind == "line" else 2
            th_d2 = th_d * th_d
            p[:, k] += r * s
            v[:, k] += r * c * th_d
            a[:, k] += -r * s * th_d2 + r * c * th_dd
            return
        if self.kind == "circle":
            ox, oy = r * (c - 1.0), r * s
            d1x, d1y = -r * s, r * c
            d2x, d2y = -ox - r, -oy  # -r cos, -r sin
        else:  # figure8
            s2 = 2.0 * s * c  # sin(2 theta)
            c2 = c * c - s * s  # cos(2 theta)
            ox, oy = r * s, (0.5 * r) * s2
            d1x, d1y = r * c, r * c2
            d2x, d2y = -ox, (-2.0 * r) * s2
        th_d2 = th_d * th_d
        p[:, 0] += ox
        p[:, 1] += oy
        v[:, 0] += d1x * th_d
        v[:, 1] += d1y * th_d
        if isinstance(th_dd, float) and th_dd == 0.0:
            a[:, 0] += d2x * th_d2
            a[:, 1] += d2y * th_d2
        else:
            a[:, 0] += d2x * th_d2 + d1x * th_dd
            a[:, 1] += d2y * th_d2 + d1y * th_dd

    def _offset_const(self, theta: float) -> np.ndarray:
        """Pattern position at phase theta minus its first point."""
        r = self._radius
        if self.kind == "circle":
            return np.array([r * (math.cos(theta) - 1.0), r * math.sin(theta), 0.0])
        if self.kind == "figure8":
            return np.array([r * math.sin(theta), 0.5 * r * math.sin(2.0 * theta), 0.0])
        if self.kind == "line":
            return np.array([r * math.sin(theta), 0.0, 0.0])
        if self.kind == "vertical":
            return np.array([0.0, 0.0, r * math.sin(theta)])
        return np.zeros(3)


def make_trajectory(cfg: TrajectoryConfig, start_position: Sequence[float] | np.ndarray) -> Trajectory:
    """The flight reference for ``cfg``, starting on the ground at ``start_position``."""
    return Trajectory(cfg, start_position)


def circle_samples(t: np.ndarray, radius: float, speed: float, height: float) -> RefSamples:
    """A horizontal circle about the origin at ``height``, sampled at times ``t`` (benchmarks, tests)."""
    t = np.asarray(t, dtype=float)
    w = speed / radius
    c, s = np.cos(w * t), np.sin(w * t)
    z = np.zeros_like(t)
    p = np.stack((radius * c, radius * s, z + height), axis=-1)
    v = np.stack((-speed * s, speed * c, z), axis=-1)
    a = np.stack((-speed * w * c, -speed * w * s, z), axis=-1)
    return RefSamples(t, p, v, a, z.copy())


@dataclass(frozen=True)
class Circle:
    """An endless horizontal circle about ``center`` at ``height``, counter-clockwise from +x (no take-off)."""

    radius: float
    speed: float
    height: float
    center: tuple[float, float] = (0.0, 0.0)

    def sample(self, t: np.ndarray) -> RefSamples:
        ref = circle_samples(t, self.radius, self.speed, self.height)
        ref.p[:, 0] += self.center[0]
        ref.p[:, 1] += self.center[1]
        return ref
