"""What a learned model can add, per axis: pure functions over one-step pairs.

The residual r is what the nominal model misses: the measured acceleration over a pair,
(v1 - v0) / dt, minus the commanded one u. Three things can take it:
- a constant (its mean);
- the fast layer: a causal first-order observer at the layer's bandwidth followed by its output
  filter, as it runs in flight (``layer_estimate``);
- a model of the state, evaluated on manoeuvres it was not fitted on.

``explained`` is the share of a residual's mean square that an estimate removes (1 - MSE after /
MSE before). ``beyond_layer`` is the score a model earns: the share of what the layer leaves that
the model and the layer together also remove. It is the number ``cfknode model check`` reports
per axis; a model with no positive score adds nothing the layer does not already do.
See docs/data.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np


class PairsLike(Protocol):
    """One-step pairs (``cfknode.models.training.Pairs``); named here so this module needs no torch."""

    x0: np.ndarray
    x1: np.ndarray
    u: np.ndarray
    dt: np.ndarray


def pair_residual(p: PairsLike) -> np.ndarray:
    """The nominal model's error per pair, (m, 3) m/s^2: measured minus commanded acceleration."""
    return (p.x1[:, 3:6] - p.x0[:, 3:6]) / p.dt[:, None] - p.u


def lowpass(t: np.ndarray, x: np.ndarray, cutoff_hz: float) -> np.ndarray:
    """Causal first-order low-pass of ``x`` (m, k) sampled at ``t``; a gap over 0.1 s restarts it."""
    if cutoff_hz <= 0.0:
        return x.copy()
    y = np.empty_like(x)
    state = x[0].copy()
    w = 2.0 * math.pi * cutoff_hz
    for i in range(x.shape[0]):
        dt = t[i] - t[i - 1] if i else 0.0
        if dt > 0.1 or dt < 0.0:
            state = x[i].copy()
        else:
            state += (1.0 - math.exp(-w * dt)) * (x[i] - state)
        y[i] = state
    return y


def layer_estimate(t: np.ndarray, r: np.ndarray, bandwidth_hz: tuple[float, float],
                   output_hz: tuple[float, float]) -> np.ndarray:
    """The layer's estimate of ``r`` (m, 3), causal: observer then output filter; (xy, z) cut-offs in Hz."""
    out = np.empty_like(r)
    for axes, k in ((slice(0, 2), 0), (slice(2, 3), 1)):
        out[:, axes] = lowpass(t, lowpass(t, r[:, axes], bandwidth_hz[k]), output_hz[k])
    return out


def explained(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Per axis, the share of ``before``'s mean square that is gone in ``after`` (1 - MSE ratio)."""
    ms = np.mean(before**2, axis=0)
    return np.where(ms > 0, 1.0 - np.mean(after**2, axis=0) / np.where(ms > 0, ms, 1.0), 0.0)


@dataclass(frozen=True)
class AxisShares:
    """Per axis (x, y, z): the residual's RMS and what each estimate removes of its mean square."""

    rms: np.ndarray  # m/s^2
    constant: np.ndarray  # share a constant (the mean) removes
    layer: np.ndarray  # share the fast layer removes
    model: np.ndarray  # share the model alone removes (held-out)
    beyond_layer: np.ndarray  # share of what the layer leaves that model + layer also remove


def shares(t: np.ndarray, r: np.ndarray, model_r: np.ndarray, bandwidth_hz: tuple[float, float],
           output_hz: tuple[float, float]) -> AxisShares:
    """The per-axis table ``cfknode model check`` prints, for residual ``r`` and a model's ``model_r``."""
    layer_left = r - layer_estimate(t, r, bandwidth_hz, output_hz)
    rest = r - model_r
    both_left = rest - layer_estimate(t, rest, bandwidth_hz, output_hz)
    return AxisShares(
        rms=np.sqrt(np.mean(r**2, axis=0)),
        constant=explained(r, r - r.mean(axis=0)),
        layer=explained(r, layer_left),
        model=explained(r, rest),
        beyond_layer=explained(layer_left, both_left),
    )


def open_loop_errors(t: np.ndarray, x: np.ndarray, u: np.ndarray, horizons_s: tuple[float, ...],
                     offset: np.ndarray | None = None,
                     model: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                     every_s: float = 0.05) -> dict[float, tuple[float, float]]:
    """RMS position and velocity error (m, m/s) after each horizon, predicting from every ``every_s``.

    Prediction: v' = u + offset(start) + model(x, u), Euler at the data's own steps with the recorded
    u. ``offset`` (m, 3) is held from each start (the layer's estimate then); ``model`` maps
    (x (k, 6), u (k, 3)) -> (k, 3). Predictions that would cross a gap over 0.1 s are not made.
    """
    dt = np.diff(t)
    out: dict[float, tuple[float, float]] = {}
    starts = np.flatnonzero(np.diff(np.floor(t / every_s), prepend=-1) > 0)
    for h in horizons_s:
        ends = np.searchsorted(t, t[starts] + h)
        ok = ends < t.size
        s_idx, e_idx = starts[ok], ends[ok]
        keep = [k for k, (a, b) in enumerate(zip(s_idx, e_idx)) if b > a and np.all(dt[a:b] <= 0.1)]
        s_idx, e_idx = s_idx[keep], e_idx[keep]
        if s_idx.size == 0:
            out[h] = (math.nan, math.nan)
            continue
        state = x[s_idx].copy()
        held = offset[s_idx] if offset is not None else np.zeros((s_idx.size, 3))
        steps = int(np.max(e_idx - s_idx))
        for j in range(steps):
            live = s_idx + j < e_idx
            i = np.minimum(s_idx + j, t.size - 2)
            step = np.where(live, dt[i], 0.0)[:, None]
            acc = u[i] + held + (model(state, u[i]) if model is not None else 0.0)
            state[:, 0:3] += step * state[:, 3:6] + 0.5 * step * step * acc
            state[:, 3:6] += step * acc
        err = state - x[e_idx]
        out[h] = (float(np.sqrt(np.mean(np.sum(err[:, 0:3] ** 2, axis=1)))),
                  float(np.sqrt(np.mean(np.sum(err[:, 3:6] ** 2, axis=1)))))
    return out


WORTH_IT = 0.10  # a model must remove at least this share of what the layer leaves on an axis


def verdict(beyond: np.ndarray, axes: str = "xyz") -> str:
    """One plain sentence: is learning worth it for this vehicle, and on which axes."""
    good = [(a, float(s)) for a, s in zip(axes, beyond) if s >= WORTH_IT]
    if not good:
        best = max(float(s) for s in beyond)
        return (f"not worth learning: on held-out manoeuvres a model removes at most {max(best, 0.0):.0%} of what "
                f"the fast layer leaves on any axis (the bar is {WORTH_IT:.0%}); fly with the layer alone.")
    named = ", ".join(f"{a} ({s:.0%})" for a, s in good)
    return (f"worth learning on {named}: on held-out manoeuvres a model removes that share of what the "
            f"fast layer leaves; elsewhere it adds under {WORTH_IT:.0%}.")


# The model file's metadata key (``ModelFile.extra``) for ``cfknode train``'s held-out ``beyond_layer`` (x, y, z).
SCORE_KEY = "beyond_layer"


def score_problem(value: object) -> str | None:
    """Why a stored score is unusable (None when it is absent or three finite numbers)."""
    if value is None:
        return None
    if not (finite_numbers(value) and len(value) == 3):
        return f"metadata 'extra.{SCORE_KEY}' must be a list of 3 finite numbers"
    return None


def finite_numbers(value: object) -> bool:
    """Whether a metadata value is a list of finite plain numbers (JSON numbers, not booleans)."""
    return isinstance(value, list) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)


def stored_score(extra: object) -> np.ndarray | None:
    """The per-axis score a model file stores (``score_problem`` checked at load); None for older files."""
    value = extra.get(SCORE_KEY) if isinstance(extra, Mapping) else None
    if value is None or score_problem(value) is not None:
        return None
    return np.asarray(value, dtype=np.float64)


def flown_axes(score: np.ndarray | None, min_score: float) -> tuple[bool, bool, bool] | None:
    """The axes a model flies on beside the layer: those whose stored score exceeds ``min_score``. None: no
    score stored (every axis flies, as before scores were stored)."""
    if score is None:
        return None
    x, y, z = (float(s) > min_score for s in score.tolist())
    return x, y, z
