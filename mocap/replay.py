"""Replay a recorded flight's mocap: the poses of a flight log's ``/mocap`` topic, at their times.

Each ``/mocap`` message was written when the flight loop received the frame (``t``) and
carries the frame's sample time (``stamp``, or ``t`` when it was not recorded). A replayed
pose has its sample time as ``Pose.t`` and becomes visible to ``latest(now)`` at its
receive time, so the recorded latency and jitter come back too. Messages logged as
dropouts (``received: false``) count as dropouts once their time has passed. A log cut
short by a crash replays up to its last complete record (``read_log`` is tolerant of that).

``time_offset`` shifts the recording onto the replaying clock: replay time = log time -
``time_offset``, so ``time_offset=12.0`` starts at the log's t = 12 s.
"""

from __future__ import annotations

import bisect
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from cfknode.flight.logreader import LogData, LogError, read_log, require_messages
from cfknode.mocap.source import MocapStats, Pose, RateMeter


class ReplayError(ValueError):
    """The log has nothing to replay; one line naming the file."""


class ReplayMocap:
    """A ``PoseSource`` over recorded poses (sorted by receive time)."""

    def __init__(self, available: Sequence[float], poses: Sequence[Pose], dropout_times: Sequence[float]) -> None:
        if len(available) != len(poses):
            raise ValueError("one availability time per pose")
        order = np.argsort(np.asarray(available, dtype=float), kind="stable")
        self._available = [float(available[i]) for i in order]
        self._poses = [poses[i] for i in order]
        self._dropouts = sorted(float(t) for t in dropout_times)
        self._meter_window = 1.0
        self._last_now = -np.inf
        self._index = 0  # poses visible so far (the loop asks with increasing times)

    @classmethod
    def from_log(cls, log: str | Path | LogData, *, time_offset: float = 0.0) -> "ReplayMocap":
        data = log if isinstance(log, LogData) else read_log(log)
        try:
            require_messages(data, ("/mocap",))
        except LogError as exc:
            raise ReplayError(str(exc)) from None
        available: list[float] = []
        poses: list[Pose] = []
        dropouts: list[float] = []
        for msg in data.topic("/mocap"):
            t = float(msg["t"]) - time_offset
            if not msg.get("received", True) or msg.get("p") is None or msg.get("q") is None:
                dropouts.append(t)
                continue
            if any(v is None for v in (*msg["p"], *msg["q"])):  # non-finite numbers are logged as null
                dropouts.append(t)
                continue
            stamp = float(msg["stamp"]) - time_offset if msg.get("stamp") is not None else t
            poses.append(Pose(stamp, msg["p"], msg["q"]))
            available.append(t)
        if not poses:
            raise ReplayError(f"{data.path}: no mocap poses to replay (topic /mocap is empty)")
        return cls(available, poses, dropouts)

    @property
    def duration(self) -> float:
        """Replay time of the last pose."""
        return self._available[-1]

    @property
    def start(self) -> float:
        return self._available[0]

    def __len__(self) -> int:
        return len(self._poses)

    def latest(self, now: float) -> Pose | None:
        # The loop asks with increasing times: walk forward; a step back in time bisects.
        if now < self._last_now:
            self._index = bisect.bisect_right(self._available, now + 1e-12)
        else:
            available = self._available
            i, n = self._index, len(available)
            while i < n and available[i] <= now + 1e-12:
                i += 1
            self._index = i
        self._last_now = now
        return self._poses[self._index - 1] if self._index > 0 else None

    def stats(self) -> MocapStats:
        now = self._last_now
        if not np.isfinite(now):
            return MocapStats(frames=0, dropouts=0, rate_hz=0.0)
        dropouts = bisect.bisect_right(self._dropouts, now + 1e-12)
        meter = RateMeter(self._meter_window)
        lo = bisect.bisect_left(self._available, now - self._meter_window)
        for t in self._available[lo:self._index]:
            meter.add(t)
        return MocapStats(frames=self._index, dropouts=dropouts, rate_hz=meter.rate(now))

    def close(self) -> None:
        """Nothing to release: the log was read whole."""

    def __repr__(self) -> str:
        return f"ReplayMocap({len(self)} poses, {self.start:.3f}..{self.duration:.3f} s)"


def replay_from_log(path: str | Path, **kwargs: Any) -> ReplayMocap:
    return ReplayMocap.from_log(path, **kwargs)
