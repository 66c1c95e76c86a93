"""Flight logs to training data: the (t, x = (p, v), u = commanded acceleration) the MPC saw.

Training learns what the flight process can observe: the estimated state and the
acceleration it commanded. Only airborne ticks where a controller was in charge are
kept (not motors-off, not sitting on the ground), and each such run is one segment.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Sequence

import numpy as np

from cfknode.app.config import ConfigError
from cfknode.app.logs.reader import LogColumns, LogData, LogError, read_columns, require_messages
from cfknode.models.training import Segment

CONTROLLED = ("mpc", "fallback", "geometric")
MIN_HEIGHT = 0.1  # m above the start: below it ground effect and contact are not the model's business
MIN_SEGMENT = 40  # ticks (0.1 s at 400 Hz); shorter runs hold no usable pairs after filtering


# What training reads of a log (as arrays: a long flight stays small in memory).
TRAINING_FIELDS: dict[str, tuple[str, ...]] = {"/state": ("p", "v"), "/command": ("acc", "source")}


def segments_from_log(log: LogData | LogColumns, name: str) -> list[Segment]:
    t_state = log.times("/state")
    t_cmd = log.times("/command")
    if t_state.size == 0 or t_cmd.size == 0:
        return []
    p, v = log.array("/state", "p"), log.array("/state", "v")
    acc, source = log.array("/command", "acc"), log.array("/command", "source")
    # Both channels are written in the same tick with the same time: join on it.
    common, i_state, i_cmd = np.intersect1d(t_state, t_cmd, return_indices=True)
    p, v, acc, source = p[i_state], v[i_state], acc[i_cmd], source[i_cmd]
    ground = np.nanmin(p[:, 2]) if p.size else 0.0
    keep = np.isin(source, CONTROLLED) & (p[:, 2] > ground + MIN_HEIGHT)
    keep &= np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(v), axis=1) & np.all(np.isfinite(acc), axis=1)
    segments = []
    for run in _runs(keep):
        if run.stop - run.start >= MIN_SEGMENT:
            x = np.concatenate((p[run], v[run]), axis=1)
            segments.append(Segment(t=common[run], x=x, u=acc[run], source=name))
    return segments


def segments_from_logs(
    paths: Sequence[str | Path], on_damage: Callable[[str], None] = lambda line: None
) -> list[Segment]:
    """All training segments from the given flight logs; a bad log is a one-line error.

    ``on_damage`` gets one line per log that was read around damage (what was skipped).
    """
    segments: list[Segment] = []
    for path in paths:
        try:
            log = read_columns(path, TRAINING_FIELDS)
            require_messages(log, ("/state", "/command"))
        except LogError as exc:
            raise ConfigError(str(exc)) from None
        if log.note:
            on_damage(f"{path}: {log.note}")
        found = segments_from_log(log, Path(path).name)
        if not found:
            raise ConfigError(f"flight log {path} holds no airborne controlled flight to train on")
        segments.extend(found)
    return segments


def _runs(mask: np.ndarray) -> list[slice]:
    """Maximal runs of True in a boolean array, as slices."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(np.int8), [0]))))
    return [slice(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]
