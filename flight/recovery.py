"""Time to recover from a step disturbance (a mass change): how long until the position error is back
under a threshold for good, and how large it got on the way.

"For good" means until the next step or the end of the pattern: an error that dips under the
threshold and rises over it again has not recovered yet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

RECOVERY_THRESHOLD_M = 0.03  # m: the position error counted as recovered


@dataclass(frozen=True)
class StepRecovery:
    t_step: float  # flight time of the step, s
    factor: float  # the step (mass / nominal mass)
    time_to_recover: float  # s from the step until the error stays under the threshold; inf: never
    peak_error: float  # m, largest error norm from the step to the next step or the end (NaN without samples)

    def to_dict(self) -> dict[str, Any]:
        return {"t": self.t_step, "factor": self.factor,
                "time_to_recover_s": self.time_to_recover if math.isfinite(self.time_to_recover) else None,
                "peak_error_m": self.peak_error}


def recovery(t: np.ndarray, err: np.ndarray, t_step: float, t_end: float,
             threshold: float = RECOVERY_THRESHOLD_M) -> tuple[float, float]:
    """(time to recover, peak error) for the step at ``t_step``, judged on samples in [t_step, t_end].

    ``t`` (n,) sample times, ``err`` (n,) error norms [m]. The time to recover is from ``t_step``
    to the first sample after which every sample up to ``t_end`` is under ``threshold`` (0 when the
    error never leaves it); ``inf`` when the last sample is not under it. Non-finite errors count as
    over the threshold. No samples in the interval: (inf, NaN).
    """
    t = np.asarray(t, dtype=float).reshape(-1)
    err = np.asarray(err, dtype=float).reshape(-1)
    if t.shape != err.shape:
        raise ValueError(f"t {t.shape} and err {err.shape} differ in shape")
    inside = (t >= t_step) & (t <= t_end)
    ts, es = t[inside], err[inside]
    if ts.size == 0:
        return math.inf, math.nan
    finite = np.isfinite(es)
    peak = float(es[finite].max()) if finite.any() else math.nan
    over = ~(finite & (es < threshold))
    if over[-1]:
        return math.inf, peak
    if not over.any():
        return 0.0, peak
    last_over = int(np.flatnonzero(over)[-1])
    return float(ts[last_over + 1] - t_step), peak


def step_recoveries(t: np.ndarray, err: np.ndarray, steps: Sequence[tuple[float, float]], t_end: float,
                    threshold: float = RECOVERY_THRESHOLD_M) -> tuple[StepRecovery, ...]:
    """``recovery`` for each (time, factor) step in time order, each judged until the next step or ``t_end``."""
    ordered = sorted((float(ts), float(f)) for ts, f in steps)
    out = []
    for i, (ts, factor) in enumerate(ordered):
        if ts > t_end:
            continue
        # Up to, not including, the next step: its own disturbance is not this one's.
        until = min(t_end, math.nextafter(ordered[i + 1][0], -math.inf)) if i + 1 < len(ordered) else t_end
        ttr, peak = recovery(t, err, ts, until, threshold)
        out.append(StepRecovery(ts, factor, ttr, peak))
    return tuple(out)


def recovery_fields(recoveries: Sequence[StepRecovery]) -> dict[str, Any]:
    """Flat summary fields: ``recovery_s_1``, ``peak_error_m_1``, ... (None when never recovered)."""
    fields: dict[str, Any] = {}
    for i, r in enumerate(recoveries, start=1):
        fields[f"step_{i}_at_s"] = r.t_step
        fields[f"step_{i}_factor"] = r.factor
        fields[f"recovery_s_{i}"] = r.time_to_recover if math.isfinite(r.time_to_recover) else None
        fields[f"peak_error_m_{i}"] = r.peak_error
    return fields


__all__ = ["RECOVERY_THRESHOLD_M", "StepRecovery", "recovery", "recovery_fields", "step_recoveries"]
