"""The motioncapture adapter: mock frames, the child-process client, deadlines, dropouts, time base."""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from types import SimpleNamespace
from typing import Any

import motioncapture
import numpy as np
import pytest

from cfknode.mocap.motioncapture_source import (
    MocapError,
    MotioncaptureSource,
    SubprocessMotionCapture,
    connect_with_deadline,
    motioncapture_config,
)
from cfknode.mocap.source import PoseSource


def body(x: float, y: float, z: float, w: float, qx: float, qy: float, qz: float) -> Any:
    """What libmotioncapture hands out: float32 position, a Quaternion with .w .x .y .z."""
    return SimpleNamespace(position=np.array([x, y, z], dtype=np.float32),
                           rotation=SimpleNamespace(w=w, x=qx, y=qy, z=qz))


class ScriptedClient:
    """A motioncapture object replaying (monotonic time, bodies) frames, then blocking until closed."""

    def __init__(self, frames: list[tuple[float, dict[str, Any]]], fail_at_end: str | None = None) -> None:
        self._frames = list(frames)
        self._fail = fail_at_end
        self._closed = threading.Event()
        self.frame_monotonic: float | None = None
        self.rigidBodies: dict[str, Any] = {}
        self.served = 0

    def waitForNextFrame(self) -> None:  # noqa: N802
        if self.served == len(self._frames):
            if self._fail:
                raise RuntimeError(self._fail)
            self._closed.wait()
            raise MocapError("closed")
        self.frame_monotonic, self.rigidBodies = self._frames[self.served]
        self.served += 1

    def close(self) -> None:
        self._closed.set()


def wait_until(predicate: Any, timeout: float = 3.0) -> bool:
    end = time.monotonic() + timeout
    while not predicate() and time.monotonic() < end:
        time.sleep(0.002)
    return predicate()


def closed_port() -> int:
    with socket.socket() as s:  # a port nothing listens on, on loopback only
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_mock_config_string_is_what_libmotioncapture_parses() -> None:
    cfg = motioncapture_config("mock", "ignored", mock_bodies={"cf231": (0.1, 0.2, 0.3, 0.5, 0.5, -0.5, 0.5)},
                               mock_rate_hz=100.0)
    assert cfg == {"rigid_bodies": "cf231(0.1,0.2,0.3,0.5,0.5,-0.5,0.5)", "frequency": "100"}
    mc = motioncapture.connect("mock", cfg)
    mc.waitForNextFrame()
    rb = mc.rigidBodies["cf231"]
    # x, y, z, then qw, qx, qy, qz: the mock's order.
    assert rb.position.tolist() == pytest.approx([0.1, 0.2, 0.3])
    assert (rb.rotation.w, rb.rotation.x, rb.rotation.y, rb.rotation.z) == pytest.approx((0.5, 0.5, -0.5, 0.5))


def test_mock_frames_parse_into_poses() -> None:
    src = MotioncaptureSource.open(
        "mock", "", "cf231",
        mock_bodies={"cf231": (1.0, -2.0, 0.5, 0.7071068, 0.0, 0.0, 0.7071068), "cf5": (9, 9, 9, 1, 0, 0, 0)},
    )
    try:
        assert isinstance(src, PoseSource)
        assert src.wait_for_frames(5, timeout=3.0)
        pose = src.latest(0.0)
        assert pose.position.dtype == np.float64
        np.testing.assert_allclose(pose.position, [1.0, -2.0, 0.5], atol=1e-6)
        np.testing.assert_allclose(pose.quaternion, [math.sqrt(0.5), 0, 0, math.sqrt(0.5)], atol=1e-6)  # w x y z
        stats = src.stats()
        assert stats.frames >= 5 and stats.dropouts == 0
        assert src.label == "mock"
    finally:
        src.close()


def test_sdk_types_run_in_a_child_process() -> None:
    # The mock type through the child-process client: the path vicon/optitrack/qualisys/vrpn take.
    cfg = motioncapture_config("mock", "", mock_bodies={"cf7": (0.25, 0.5, 1.0, 1, 0, 0, 0)})
    client = SubprocessMotionCapture("mock", cfg, timeout=10.0)
    src = MotioncaptureSource(client, "cf7", label="mock (child)").start()
    try:
        assert src.wait_for_frames(3, timeout=5.0)
        np.testing.assert_allclose(src.latest(0.0).position, [0.25, 0.5, 1.0], atol=1e-6)
        assert client.frame_monotonic is not None and client.frame_monotonic <= time.monotonic()
    finally:
        src.close()
    assert client._proc.poll() is not None  # the child is gone


def test_a_silent_vicon_host_fails_within_the_deadline() -> None:
    host = f"127.0.0.1:{closed_port()}"
    start = time.monotonic()
    with pytest.raises(MocapError) as info:
        MotioncaptureSource.open("vicon", host, "cf231", timeout=1.0)
    elapsed = time.monotonic() - start
    message = str(info.value)
    assert message.startswith(f"no answer from vicon at {host} within 1 s")
    assert "\n" not in message
    assert elapsed < 4.0  # libmotioncapture alone would loop forever (holding the GIL)


def test_a_refused_qualisys_connection_is_one_clear_line() -> None:
    port = closed_port()
    with pytest.raises(MocapError) as info:
        MotioncaptureSource.open("qualisys", f"127.0.0.1:{port}", "cf231", timeout=5.0)
    message = str(info.value)
    assert message.startswith(f"could not connect to qualisys at 127.0.0.1:{port}: ")
    assert "\n" not in message


def test_connect_deadline_and_errors_with_an_injected_connector() -> None:
    hang = threading.Event()
    with pytest.raises(MocapError, match=r"^no answer from optitrack at 10\.1\.2\.3 within 0\.2 s"):
        connect_with_deadline(lambda t, c: hang.wait(), "optitrack", {"hostname": "10.1.2.3"}, 0.2)
    hang.set()

    def boom(t: str, c: dict) -> Any:
        raise RuntimeError("Unknown motion capture type!\nmore detail")

    with pytest.raises(MocapError, match=r"^could not connect to vrpn at h: RuntimeError: Unknown motion capture type!$"):
        connect_with_deadline(boom, "vrpn", {"hostname": "h"}, 1.0)
    seen: list[tuple[str, dict]] = []
    client = ScriptedClient([])
    assert connect_with_deadline(lambda t, c: seen.append((t, c)) or client, "vicon", {"hostname": "h"}, 1.0) is client
    assert seen == [("vicon", {"hostname": "h"})]


def test_config_per_type() -> None:
    assert motioncapture_config("vicon", "10.0.0.5:801") == {"hostname": "10.0.0.5:801"}
    assert motioncapture_config("optitrack", "10.0.0.5") == {"hostname": "10.0.0.5"}
    assert motioncapture_config("qualisys", "10.0.0.5:22223") == {"hostname": "10.0.0.5", "port": "22223"}
    assert motioncapture_config("vrpn", "tracker") == {"hostname": "tracker"}
    with pytest.raises(MocapError, match="unknown mocap type 'nokov'"):
        motioncapture_config("nokov", "h")
    with pytest.raises(MocapError, match="vicon needs a host"):
        motioncapture_config("vicon", "")


def test_occlusion_and_bad_values_are_dropouts_and_the_order_is_wxyz() -> None:
    good = body(1, 2, 3, 0.0, 0.0, 0.0, 2.0)  # unnormalised: stored normalised
    frames = [
        (100.00, {"cf1": good}),
        (100.01, {"other": good}),  # occluded: the SDK omits the body
        (100.02, {"cf1": body(float("nan"), 0, 0, 1, 0, 0, 0)}),
        (100.03, {"cf1": body(0, 0, 0, 0, 0, 0, 0)}),  # zero quaternion
        (100.04, {"cf1": body(4, 5, 6, 0.5, -0.5, 0.5, -0.5)}),
    ]
    client = ScriptedClient(frames)
    poses: list[Any] = []
    src = MotioncaptureSource(client, "cf1", on_pose=poses.append).start()
    try:
        assert wait_until(lambda: client.served == 5 and src.status().stream_frames == 5)
        status = src.status()
        assert (status.frames, status.dropouts, status.stream_frames) == (2, 3, 5)
        assert [p.t for p in poses] == [100.00, 100.04]  # stamped with the frame's monotonic time
        np.testing.assert_allclose(poses[0].quaternion, [0, 0, 0, 1])
        np.testing.assert_allclose(poses[1].position, [4, 5, 6])
        np.testing.assert_allclose(poses[1].quaternion, [0.5, -0.5, 0.5, -0.5])
        assert src.latest(0.0) is poses[1]
    finally:
        src.close()


def test_time_base_moves_poses_onto_the_flight_clock() -> None:
    now = time.monotonic()
    client = ScriptedClient([(now - 0.02, {"cf1": body(0, 0, 0, 1, 0, 0, 0)})])
    src = MotioncaptureSource(client, "cf1").start()
    try:
        assert src.wait_for_frames(1, 2.0)
        flight_zero = time.monotonic()
        src.set_time_base(lambda: time.monotonic() - flight_zero)  # a wall clock starting now
        t = src.latest(0.0).t
        assert -0.5 < t < 0.0  # the pre-flight frame is now slightly before flight time 0
        assert src.stats().frames == 1
    finally:
        src.close()


def test_rate_outside_the_band_is_warned_once(caplog: pytest.LogCaptureFixture) -> None:
    b = body(0, 0, 0, 1, 0, 0, 0)
    t0 = 5000.0
    slow = [(t0 + k / 50.0, {"cf1": b}) for k in range(120)]  # 50 Hz for 2.4 s
    fast = [(slow[-1][0] + (k + 1) / 100.0, {"cf1": b}) for k in range(250)]  # then 100 Hz
    client = ScriptedClient(slow + fast)
    with caplog.at_level(logging.INFO, logger="cfknode.mocap"):
        src = MotioncaptureSource(client, "cf1", label="vicon at h").start()
        try:
            assert wait_until(lambda: client.served == len(slow) + len(fast) and src.status().stream_frames == 370)
        finally:
            src.close()
    texts = [text for _, text in src.warnings]
    assert texts[0] == "vicon at h: cf1 arrives at 50 Hz, outside 80-120 Hz"
    assert texts[1].startswith("vicon at h: cf1 back at ") and len(texts) == 2
    assert "outside 80-120 Hz" in caplog.text


def test_stream_errors_end_the_reader_and_are_reported() -> None:
    client = ScriptedClient([(1.0, {"cf1": body(0, 0, 0, 1, 0, 0, 0)})], fail_at_end="vicon: connection reset")
    src = MotioncaptureSource(client, "cf1").start()
    try:
        assert wait_until(lambda: src.status().error is not None)
        assert src.status().error == "RuntimeError: vicon: connection reset"
        assert src.latest(0.0) is not None  # the last pose stays for the safety layer to age out
    finally:
        src.close()


def test_a_failing_listener_does_not_stop_the_stream() -> None:
    frames = [(float(k), {"cf1": body(k, 0, 0, 1, 0, 0, 0)}) for k in range(3)]
    client = ScriptedClient(frames)

    def bad(pose: Any) -> None:
        raise ValueError("consumer bug")

    src = MotioncaptureSource(client, "cf1", on_pose=bad).start()
    try:
        assert wait_until(lambda: src.status().frames == 3)
        assert src.latest(0.0).position[0] == 2.0
    finally:
        src.close()
