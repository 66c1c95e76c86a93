"""Where a simulated flight's residual comes from: the plant's acceleration minus the command, split by cause.

The residual a learned model is trained on is the measured acceleration minus the commanded one. Per axis,
over the pattern, this gives its RMS and mean; the RMS left against the command delayed by ``tau`` (a lag
between command and acceleration, which the MPC's v' = u leaves out: the attitude loop's, the motors');
and a least-squares slope on the velocity (what a model of (v, u) can take on this trajectory, with its
R^2). Simulated logs only: it differentiates the plant's true velocity (``/state`` ``v_true``). The
numbers of docs/results.md#why-the-learner-does-not-beat-the-layer-what-the-residual-is-2026-12-03 are its
output: ``python -m cfknode.app.logs.residual_split LOG.mcap``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

DELAYS_S = (0.0, 0.02, 0.04, 0.06, 0.08, 0.1, 0.12, 0.15, 0.2)


def accelerations(t_state: np.ndarray, v: np.ndarray, t_cmd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(velocity, acceleration) at the command times ``t_cmd``: ``v`` (n, 3) at ``t_state`` interpolated, then
    differentiated (central differences)."""
    vi = np.stack([np.interp(t_cmd, t_state, v[:, k]) for k in range(3)], axis=1)
    return vi, np.gradient(vi, t_cmd, axis=0)


def delay_rms(t: np.ndarray, u: np.ndarray, a: np.ndarray, delays: Sequence[float], sel: np.ndarray) -> np.ndarray:
    """(len(delays), 3): per axis, the RMS over ``sel`` of the acceleration ``a`` minus the command ``u`` as it
    was ``tau`` earlier (held at its first value before the log's start)."""
    out = np.empty((len(delays), 3))
    for i, tau in enumerate(delays):
        late = np.stack([np.interp(t - tau, t, u[:, k]) for k in range(3)], axis=1)
        out[i] = np.sqrt(np.mean((a - late)[sel] ** 2, axis=0))
    return out


def velocity_slope(v: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per axis, the least-squares slope of ``r`` on ``v`` with a constant, and the fit's R^2 (0 for an axis
    whose residual does not vary beyond rounding)."""
    slopes, r2 = np.zeros(3), np.zeros(3)
    for k in range(3):
        x = np.column_stack((v[:, k], np.ones(v.shape[0])))
        coef, *_ = np.linalg.lstsq(x, r[:, k], rcond=None)
        var = float(np.var(r[:, k]))
        slopes[k] = coef[0]
        varies = var > 1e-20 * (1.0 + float(np.mean(r[:, k])) ** 2)
        r2[k] = 1.0 - float(np.var(r[:, k] - x @ coef)) / var if varies else 0.0
    return slopes, r2


def split(t_state: np.ndarray, v: np.ndarray, t_cmd: np.ndarray, u: np.ndarray, window: tuple[float, float],
          delays: Sequence[float] = DELAYS_S) -> dict[str, Any]:
    """The split over ``window`` (s of flight time): residual RMS and mean, RMS against each delayed command,
    the best delay, the velocity slope and its R^2, all per axis (x, y, z)."""
    vi, a = accelerations(t_state, v, t_cmd)
    sel = (t_cmd > window[0]) & (t_cmd < window[1])
    if not sel.any():
        raise ValueError(f"no commands in the window {window}")
    r = a - u
    by_delay = delay_rms(t_cmd, u, a, delays, sel)
    slopes, r2 = velocity_slope(vi[sel], r[sel])
    horizontal = by_delay[:, :2].sum(axis=1)
    return {
        "residual_rms": np.sqrt(np.mean(r[sel] ** 2, axis=0)).tolist(),
        "residual_mean": np.mean(r[sel], axis=0).tolist(),
        "delays_s": list(delays),
        "rms_against_delayed_command": by_delay.tolist(),
        "best_horizontal_delay_s": float(delays[int(np.argmin(horizontal))]),
        "velocity_slope": slopes.tolist(),
        "velocity_r2": r2.tolist(),
    }


def split_log(path: str | Path) -> dict[str, Any]:
    """``split`` of a simulated flight log over its summary's pattern window."""
    from cfknode.app.logs.reader import read_log

    log = read_log(path)
    state, command, summary = log.topic("/state"), log.topic("/command"), log.topic("/summary")
    if not state or "v_true" not in state[0]:
        raise ValueError(f"{path}: no plant velocity (/state v_true): a simulated flight's log is needed")
    if not command or not summary:
        raise ValueError(f"{path}: no /command or /summary messages")
    t_state = np.array([m["t"] for m in state])
    v = np.array([m["v_true"] for m in state], dtype=float)
    t_cmd = np.array([m["t"] for m in command])
    u = np.array([m["acc"] for m in command], dtype=float)
    w0, w1 = summary[0]["window"]
    return split(t_state, v, t_cmd, u, (float(w0), float(w1)))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m cfknode.app.logs.residual_split", description=__doc__.split("\n")[0])
    parser.add_argument("logs", nargs="+", help="simulated flight logs (.mcap)")
    args = parser.parse_args(argv)
    for path in args.logs:
        print(json.dumps({"log": str(path), **split_log(path)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["DELAYS_S", "accelerations", "delay_rms", "main", "split", "split_log", "velocity_slope"]
