"""A flight table to training segments: input to acceleration, glitch masks, time alignment, subsampling.

Each step is a pure function of arrays and reports what it did (``Preparation``), so ``cfknode
train`` and ``cfknode model check`` can say how much of a dataset they used and why.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from cfknode.app.data import inputs
from cfknode.kernel.errors import ConfigError
from cfknode.models.training import Segment

MIN_SEGMENT = 20  # samples; shorter runs between glitches hold no usable pairs after filtering


@dataclass(frozen=True)
class TableOptions:
    """How a table's input becomes an acceleration, and how glitches and lags are handled."""

    mass: float  # kg
    gravity: float  # m/s^2
    newton_per_cmd: float  # N per unit of the RPYT thrust command (the vehicle's map)
    thrust_coefficient: float | None = None  # N/(rad/s)^2, needed with motor speeds
    max_speed: float = 10.0  # m/s: a position step implying more is a state jump
    max_accel: float = 60.0  # m/s^2: a velocity step implying more is a state jump
    spike_mads: float = 10.0  # an input this many median absolute deviations off its neighbours is a spike
    align: str = "auto"  # "auto" (estimated), "none", or a lag in seconds
    max_lag_s: float = 0.1  # the estimated lag is searched within +- this
    every: int = 1  # keep every n-th sample (after the masks and the alignment)


@dataclass(frozen=True)
class Preparation:
    """What was done to one table."""

    name: str
    rows: int
    rate_hz: float
    input_kind: str  # "motors", "thrust" or "rpyt"
    non_finite: int  # rows masked for a missing or non-finite value
    jumps: int  # rows masked around a state jump
    spikes: int  # rows masked around an input spike
    lag_s: float  # input delay applied (estimated, or given)
    segments: int
    samples: int  # samples in the segments, after subsampling

    def line(self) -> str:
        return (f"{self.name}: {self.rows} rows at {self.rate_hz:.0f} Hz, input {self.input_kind}; masked "
                f"{self.non_finite} non-finite, {self.jumps} at state jumps, {self.spikes} at input spikes; "
                f"input lag {self.lag_s * 1e3:+.0f} ms; {self.segments} segment(s), {self.samples} samples")


def commanded_acceleration(table: Mapping[str, np.ndarray], opts: TableOptions, where: str) -> tuple[np.ndarray, str]:
    """u (n, 3) from whichever input the table has, and its kind."""
    q = _quaternion(table)
    if all(f"m{i}" in table for i in range(1, 5)):
        if opts.thrust_coefficient is None:
            raise ConfigError(f"{where}: motor speeds need --thrust-coefficient (N per (rad/s)^2)")
        if q is None:
            raise ConfigError(f"{where}: motor speeds need the attitude (qw qx qy qz)")
        speeds = np.stack([table[f"m{i}"] for i in range(1, 5)], axis=1)
        thrust = inputs.motor_thrust(speeds, opts.thrust_coefficient)
        return inputs.acceleration(inputs.body_z(q), thrust, opts.mass, opts.gravity), "motors"
    if "thrust" in table:
        if q is None:
            raise ConfigError(f"{where}: a thrust column needs the attitude (qw qx qy qz)")
        return inputs.acceleration(inputs.body_z(q), table["thrust"], opts.mass, opts.gravity), "thrust"
    if all(k in table for k in ("roll_deg", "pitch_deg", "thrust_cmd")):
        yaw = inputs.yaw_of(q) if q is not None else np.zeros_like(table["t"])
        direction = inputs.body_z_from_euler(np.radians(table["roll_deg"]), np.radians(table["pitch_deg"]), yaw)
        thrust = inputs.pwm_thrust(table["thrust_cmd"], opts.newton_per_cmd)
        return inputs.acceleration(direction, thrust, opts.mass, opts.gravity), "rpyt"
    raise ConfigError(f"{where}: no input columns: give m1..m4 (with --thrust-coefficient), thrust, "
                      "or roll_deg, pitch_deg and thrust_cmd (docs/data.md)")


def _quaternion(table: Mapping[str, np.ndarray]) -> np.ndarray | None:
    if not all(k in table for k in ("qw", "qx", "qy", "qz")):
        return None
    q = np.stack([table[k] for k in ("qw", "qx", "qy", "qz")], axis=1)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    return q / np.where(norm > 0, norm, 1.0)


def velocity(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Velocity from positions by central differences (one-sided at the ends)."""
    return np.gradient(p, t, axis=0)


def grow(mask: np.ndarray, k: int) -> np.ndarray:
    """``mask`` widened by ``k`` samples on each side."""
    out = mask.copy()
    for s in range(1, k + 1):
        out[s:] |= mask[:-s]
        out[:-s] |= mask[s:]
    return out


def jump_mask(t: np.ndarray, p: np.ndarray, v: np.ndarray, opts: TableOptions) -> np.ndarray:
    """Rows next to a step in position or velocity that no Crazyflie flies (an estimate reset, a mocap swap)."""
    dt = np.maximum(np.diff(t), 1e-9)
    bad = (np.linalg.norm(np.diff(p, axis=0), axis=1) / dt > opts.max_speed)
    bad |= (np.linalg.norm(np.diff(v, axis=0), axis=1) / dt > opts.max_accel)
    mask = np.zeros(t.size, dtype=bool)
    mask[1:] |= bad
    mask[:-1] |= bad
    return grow(mask, 2)


def spike_mask(u: np.ndarray, mads: float) -> np.ndarray:
    """Rows whose input is far from both neighbours' mean, in robust units (telemetry spikes)."""
    mask = np.zeros(u.shape[0], dtype=bool)
    if u.shape[0] < 5:
        return mask
    dev = u[1:-1] - 0.5 * (u[:-2] + u[2:])
    mad = np.median(np.abs(dev - np.median(dev, axis=0)), axis=0)
    scale = np.where(mad > 0, 1.4826 * mad, np.inf)
    mask[1:-1] = np.any(np.abs(dev) > mads * scale, axis=1)
    return grow(mask, 1)


def estimate_lag(t: np.ndarray, u: np.ndarray, v: np.ndarray, max_lag_s: float) -> float:
    """The delay (s) by which the measured acceleration follows the input: the best-correlated shift.

    Correlates the detrended input with the velocity's derivative over shifts within +-``max_lag_s``
    (a positive lag: the vehicle responds after the input)."""
    dt = float(np.median(np.diff(t)))
    a = np.gradient(v, t, axis=0)
    uc, ac = u - u.mean(axis=0), a - a.mean(axis=0)
    max_k = max(1, int(round(max_lag_s / dt)))
    best, best_k = -np.inf, 0
    n = t.size
    for k in range(-max_k, max_k + 1):
        x, y = (uc[: n - k], ac[k:]) if k >= 0 else (uc[-k:], ac[: n + k])
        if x.shape[0] < 10:
            continue
        c = float(np.sum(x * y)) / max(float(np.sqrt(np.sum(x * x) * np.sum(y * y))), 1e-12)
        if c > best:
            best, best_k = c, k
    return best_k * dt


def shift_input(t: np.ndarray, u: np.ndarray, lag_s: float) -> np.ndarray:
    """u delayed by ``lag_s``: the input that acts at t is the one given at t - lag."""
    if lag_s == 0.0:
        return u
    return np.stack([np.interp(t - lag_s, t, u[:, k]) for k in range(3)], axis=1)


def prepare(table: Mapping[str, np.ndarray], name: str, opts: TableOptions) -> tuple[list[Segment], Preparation]:
    """Segments (split at masks, gaps and manoeuvre changes) from one table, and what was done."""
    t = table["t"]
    if np.any(np.diff(t) <= 0):
        raise ConfigError(f"{name}: column t must increase strictly (found a step back or a repeat)")
    p = np.stack([table[k] for k in ("px", "py", "pz")], axis=1)
    v = (np.stack([table[k] for k in ("vx", "vy", "vz")], axis=1) if all(k in table for k in ("vx", "vy", "vz"))
         else velocity(t, p))
    u, kind = commanded_acceleration(table, opts, name)
    finite = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(v), axis=1) & np.all(np.isfinite(u), axis=1)
    p, v, u = (np.where(finite[:, None], a, 0.0) for a in (p, v, u))  # masked rows stay masked below
    jumps = jump_mask(t, p, v, opts) & finite
    spikes = spike_mask(u, opts.spike_mads) & finite & ~jumps
    good = finite & ~jumps & ~spikes
    lag = _lag(t[good], u[good], v[good], opts)
    u = shift_input(t, u, lag)
    groups = table.get("manoeuvre")
    segments = _segments(t, np.concatenate((p, v), axis=1), u, good, groups, name, opts.every)
    rate = 1.0 / float(np.median(np.diff(t)))
    prep = Preparation(name, int(t.size), rate, kind, int((~finite).sum()), int(jumps.sum()), int(spikes.sum()),
                       lag, len(segments), int(sum(s.t.size for s in segments)))
    return segments, prep


def _lag(t: np.ndarray, u: np.ndarray, v: np.ndarray, opts: TableOptions) -> float:
    if opts.align == "none":
        return 0.0
    if opts.align == "auto":
        return estimate_lag(t, u, v, opts.max_lag_s) if t.size > 50 else 0.0
    try:
        return float(opts.align)
    except ValueError:
        raise ConfigError(f"--align must be auto, none or a lag in seconds, got {opts.align[:40]!r}") from None


def _segments(t: np.ndarray, x: np.ndarray, u: np.ndarray, good: np.ndarray, groups: np.ndarray | None,
              name: str, every: int) -> list[Segment]:
    boundary = np.zeros(t.size, dtype=bool)
    if groups is not None:
        boundary[1:] = groups[1:] != groups[:-1]
    out = []
    edges = np.flatnonzero(np.diff(np.concatenate(([0], good.astype(np.int8), [0]))))
    for a, b in zip(edges[::2], edges[1::2]):
        cuts = [a, *(np.flatnonzero(boundary[a + 1:b]) + a + 1), b]
        for lo, hi in zip(cuts[:-1], cuts[1:]):
            sl = slice(int(lo), int(hi), max(1, every))
            if (hi - lo) // max(1, every) < MIN_SEGMENT:
                continue
            group = f":{groups[lo]}" if groups is not None else ""
            out.append(Segment(t=t[sl], x=x[sl], u=u[sl], source=f"{name}{group}"))
    return out
