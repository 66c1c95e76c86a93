"""Per-drone references for a fleet: one pattern, offset per robot.

- ``ring``: drone i flies the pattern rotated by 2 pi i / N about its centre, so N drones are
  evenly spaced around one circle (phase offsets); each takes off straight up from below its
  first point.
- ``stack``: every drone flies the same circle, drone i ``stack_spacing * i`` higher. They
  start side by side on the ground (``ground_spacing`` apart) and each stays on the pattern
  long enough longer than the one below to land ``ground_spacing`` further along the circle,
  so no two land on the same spot.
- ``crossing``: two drones; the first flies the pattern (a line: back and forth through its
  centre), the second hovers ``stack_spacing`` above the pattern's centre for as long, so the
  first passes under its wake at every crossing. The second starts ``ground_spacing`` to the
  side and lands straight down at the centre.

``HoldableReference`` lets the fleet freeze one drone's reference where the drone is (hover
in place), e.g. when two drones came too close, or glide it clear of the drones below first.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Mapping, Sequence

import numpy as np

from cfknode.flight.settings import TrajectoryConfig
from cfknode.flight.trajectory import make_trajectory
from cfknode.kernel.reference import Reference, RefSamples


class _Wrapped:
    """A reference with the span and segments of ``_inner``."""

    _inner: Reference

    @property
    def duration(self) -> float:
        return self._inner.duration

    @property
    def segments(self) -> Mapping[str, tuple[float, float]]:
        return self._inner.segments

    @property
    def pattern_window(self) -> tuple[float, float]:
        return self._inner.segments["pattern"]


class RotatedReference(_Wrapped):
    """``inner`` rotated by ``angle`` (rad) about the vertical axis through ``center`` (x, y)."""

    def __init__(self, inner: Reference, center: Sequence[float], angle: float) -> None:
        self._inner = inner
        self._c = np.array([center[0], center[1], 0.0])
        c, s = math.cos(angle), math.sin(angle)
        self._r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    @property
    def final_position(self) -> np.ndarray:
        return self._c + self._r @ (self._inner.final_position - self._c)

    def sample(self, t: np.ndarray) -> RefSamples:
        ref = self._inner.sample(t)
        rt = self._r.T
        return RefSamples(t=ref.t, p=(ref.p - self._c) @ rt + self._c, v=ref.v @ rt, a=ref.a @ rt, yaw=ref.yaw)


class HoldableReference(_Wrapped):
    """``inner``, until ``hold(t, p)``: from then on, hover at ``p`` (zero velocity and acceleration)."""

    def __init__(self, inner: Reference) -> None:
        self._inner = inner
        self._hold: tuple[float, np.ndarray, float, np.ndarray, float] | None = None

    @property
    def inner(self) -> Reference:
        return self._inner

    @property
    def held_since(self) -> float | None:
        return None if self._hold is None else self._hold[0]

    @property
    def final_position(self) -> np.ndarray:
        return self._inner.final_position

    def hold(self, t: float, p: Sequence[float], to: Sequence[float] | None = None, move_s: float = 0.0) -> None:
        """Hover at ``p`` from time ``t`` (the first hold wins); with ``to``, glide from ``p`` to ``to``
        over ``move_s`` seconds (a smootherstep: it starts and ends at rest), then hover there."""
        if self._hold is None:
            yaw = float(self._inner.sample(np.array([t])).yaw[0])
            start = np.array(p, dtype=float)
            end = start if to is None else np.array(to, dtype=float)
            self._hold = (float(t), start, yaw, end, max(float(move_s), 1e-3))

    @property
    def hold_target(self) -> np.ndarray | None:
        """Where the held drone hovers once its glide ends (None: not held)."""
        return None if self._hold is None else self._hold[3].copy()

    def sample(self, t: np.ndarray) -> RefSamples:
        if self._hold is None:
            return self._inner.sample(t)
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        t0, p, yaw, end, move_s = self._hold
        ref = self._inner.sample(t)
        after = t >= t0
        if not after.any():
            return ref
        ref_p, ref_v, ref_a, ref_yaw = ref.p.copy(), ref.v.copy(), ref.a.copy(), ref.yaw.copy()
        s, ds, dds = _smootherstep((t[after] - t0) / move_s)
        d = end - p
        ref_p[after] = p + s[:, None] * d
        ref_v[after] = (ds / move_s)[:, None] * d
        ref_a[after] = (dds / move_s**2)[:, None] * d
        ref_yaw[after] = yaw
        return RefSamples(t=t, p=ref_p, v=ref_v, a=ref_a, yaw=ref_yaw)


def _smootherstep(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The quintic 0 -> 1 and its first two derivatives (zero at both ends), for tau clipped to [0, 1]."""
    x = np.clip(tau, 0.0, 1.0)
    inside = (tau > 0.0) & (tau < 1.0)
    s = x**3 * (10.0 + x * (6.0 * x - 15.0))
    ds = np.where(inside, 30.0 * x**2 * (1.0 - x) ** 2, 0.0)
    dds = np.where(inside, 60.0 * x * (1.0 - x) * (1.0 - 2.0 * x), 0.0)
    return s, ds, dds


def fleet_references(
    cfg: TrajectoryConfig, n: int, layout: str, ground_z: float, stack_spacing: float, ground_spacing: float
) -> list[tuple[np.ndarray, Reference]]:
    """(start position, reference) for each of ``n`` drones flying ``cfg`` in ``layout``."""
    if n < 1:
        raise ValueError("a fleet needs at least one drone")
    center = (float(cfg.center[0]), float(cfg.center[1]))
    if layout == "ring":
        start = _under_first_point(cfg, ground_z)
        base = make_trajectory(cfg, start)
        out: list[tuple[np.ndarray, Reference]] = []
        for i in range(n):
            ref = RotatedReference(base, center, 2.0 * math.pi * i / n)
            out.append((ref.sample(np.zeros(1)).p[0].copy(), ref))
        return out
    if layout == "stack":
        out = []
        for i in range(n):
            level = dataclasses.replace(cfg, height=cfg.height + i * stack_spacing,
                                        duration=_stack_duration(cfg, i, ground_spacing))
            start = _under_first_point(level, ground_z) + np.array([0.0, i * ground_spacing, 0.0])
            out.append((start, make_trajectory(level, start)))
        return out
    if layout == "crossing":
        if n != 2:
            raise ValueError(f"the crossing layout flies two drones, not {n}")
        start = _under_first_point(cfg, ground_z)
        above = dataclasses.replace(cfg, kind="hover", height=cfg.height + stack_spacing)
        start_above = np.array([center[0], center[1] + ground_spacing, ground_z])
        return [(start, make_trajectory(cfg, start)), (start_above, make_trajectory(above, start_above))]
    raise ValueError(f"unknown fleet layout {layout!r} (ring, stack or crossing)")


def _under_first_point(cfg: TrajectoryConfig, ground_z: float) -> np.ndarray:
    """On the ground right below the pattern's first point."""
    probe = make_trajectory(cfg, (0.0, 0.0, ground_z))
    first = probe.sample(np.array([probe.segments["takeoff"][1]])).p[0]
    return np.array([first[0], first[1], ground_z])


def _stack_duration(cfg: TrajectoryConfig, level: int, ground_spacing: float) -> float:
    """Pattern duration of stack level ``level``: its landing spot ``level * ground_spacing`` (chord)
    further along the circle than the lowest drone's.

    The pattern's end phase is omega * g(duration), g(d) = d - min(ramp, d / 2) (the ramp-in and
    ramp-out each lose half a ramp of full-speed time, and short patterns shrink the ramp)."""
    if level == 0 or cfg.kind != "circle":
        return cfg.duration
    chord = min(ground_spacing, 2.0 * cfg.radius)
    phase = level * 2.0 * math.asin(chord / (2.0 * cfg.radius))
    ramp = cfg.ramp_duration
    target = cfg.duration - min(ramp, 0.5 * cfg.duration) + phase * cfg.radius / cfg.speed
    return 2.0 * target if target <= ramp else target + ramp


def stack_level(cfg: TrajectoryConfig, level: int, stack_spacing: float, ground_spacing: float) -> TrajectoryConfig:
    """The pattern of stack level ``level``: ``stack_spacing * level`` higher, and long enough longer
    to land ``ground_spacing`` further along the circle than level 0 (as ``fleet_references`` flies it)."""
    return dataclasses.replace(cfg, height=cfg.height + level * stack_spacing,
                               duration=_stack_duration(cfg, level, ground_spacing))
