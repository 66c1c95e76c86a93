"""Replaying a flight log's /mocap poses: timing, latency, dropouts, offsets, truncated logs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cfknode.app.logs.writer import Chunks, FlightLog, read_log
from cfknode.app.logs.reader import replay_mocap
from cfknode.mocap.replay import ReplayError, ReplayMocap
from cfknode.mocap.source import PoseSource


def _from_log(log, time_offset: float = 0.0) -> ReplayMocap:
    return replay_mocap(log, time_offset=time_offset)

LATENCY = 0.004


def frame(k: int) -> tuple[np.ndarray, np.ndarray]:
    yaw = 0.01 * k
    return np.array([0.01 * k, -0.02 * k, 1.0]), np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def write_flight(tmp_path: Path, frames: int = 300, dropped: tuple[int, ...] = (7, 8, 150)) -> Path:
    """A log like the flight loop writes: a frame sampled at k/100 s, received LATENCY later."""
    with FlightLog.create(tmp_path, {"sim": {"seed": 0}}, "test", "replay", chunks=Chunks(2048)) as log:
        for k in range(frames):
            stamp = k / 100.0
            if k in dropped:
                log.write("/mocap", stamp + LATENCY, {"received": False})
                continue
            p, q = frame(k)
            log.write("/mocap", stamp + LATENCY, {"p": p, "q": q, "received": True, "stamp": stamp})
            log.write("/tick", stamp + LATENCY, {"compute_s": 1e-4, "solve_s": 0.0, "missed": False, "mpc_ok": True})
    return log.path


def test_poses_come_back_at_their_receive_time_with_their_sample_time(tmp_path: Path) -> None:
    replay = _from_log(write_flight(tmp_path))
    assert isinstance(replay, PoseSource)
    assert len(replay) == 297
    assert replay.latest(0.0) is None  # the first frame is received at 4 ms
    assert replay.latest(LATENCY - 1e-6) is None
    first = replay.latest(LATENCY)
    assert first.t == pytest.approx(0.0)  # Pose.t is the sample time: the latency is preserved
    np.testing.assert_allclose(first.position, frame(0)[0])
    pose = replay.latest(0.1234)  # newest received by then: sampled at 0.11 s
    assert pose.t == pytest.approx(0.11)
    np.testing.assert_allclose(pose.position, frame(11)[0])
    np.testing.assert_allclose(pose.quaternion, frame(11)[1])
    assert replay.latest(0.1234) is pose  # asking again gives the same frame
    assert replay.latest(99.0).t == pytest.approx(2.99)
    assert replay.duration == pytest.approx(2.99 + LATENCY)


def test_dropouts_hold_the_previous_pose_and_are_counted(tmp_path: Path) -> None:
    replay = _from_log(write_flight(tmp_path))
    assert replay.latest(0.06 + LATENCY).t == pytest.approx(0.06)
    assert replay.latest(0.085).t == pytest.approx(0.06)  # frames 7 and 8 were lost
    assert replay.stats().dropouts == 2
    assert replay.latest(0.09 + LATENCY).t == pytest.approx(0.09)
    replay.latest(2.0)
    stats = replay.stats()
    assert stats.dropouts == 3 and stats.frames == 197  # k = 0..199 received by 2 s, three lost
    assert stats.rate_hz == pytest.approx(100.0, rel=0.03)


def test_time_offset_and_going_back_in_time(tmp_path: Path) -> None:
    replay = _from_log(write_flight(tmp_path), time_offset=1.0)
    assert replay.latest(0.0).t == pytest.approx(-0.01)  # the frame of log t = 0.99 s
    assert replay.latest(0.6 + LATENCY).t == pytest.approx(0.6)
    assert replay.latest(-0.5).t == pytest.approx(-0.51)  # a step back bisects
    assert replay.latest(-2.0) is None


def test_a_truncated_log_replays_up_to_where_it_ends(tmp_path: Path) -> None:
    path = write_flight(tmp_path)
    full = _from_log(path)
    raw = path.read_bytes()
    counts = []
    for cut in np.linspace(len(raw) * 0.3, len(raw) - 1, 6).astype(int):
        cut_path = tmp_path / "cut.mcap"
        cut_path.write_bytes(raw[:cut])
        data = read_log(cut_path)
        assert data.truncated
        part = _from_log(data)
        counts.append(len(part))
        # A prefix of the full replay, pose for pose.
        t_end = part.duration
        np.testing.assert_allclose(part.latest(t_end).position, full.latest(t_end).position)
        assert part.latest(t_end + 10.0) is part.latest(t_end)
    assert counts == sorted(counts) and counts[0] < counts[-1] <= len(full)


def test_a_log_without_mocap_is_a_clear_error(tmp_path: Path) -> None:
    with FlightLog.create(tmp_path, {}, "test", "empty") as log:
        log.write("/events", 0.0, {"level": "info", "text": "nothing flew"})
    with pytest.raises(ReplayError, match=r"empty\.mcap: no mocap poses to replay"):
        _from_log(log.path)
