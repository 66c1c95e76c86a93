"""Hardware mocap through libmotioncapture (``motioncapture`` on PyPI): vicon, optitrack, qualisys, vrpn.

A reader thread calls ``waitForNextFrame()`` and turns the rigid body named like the robot
into a ``Pose`` stamped with the host's monotonic clock when the frame arrived (the Python
bindings expose no SDK timestamp: docs/hardware.md#mocap), shifted onto the flight clock. A frame without
the body (occluded: the SDKs silently omit it) counts as a dropout. The quaternion comes as
``.w .x .y .z`` attributes and is stored scalar-first.

``waitForNextFrame`` blocks until the next frame; it runs in the reader thread only.
``motioncapture.connect`` may hang holding the GIL, so the SDK types run in a child process
(sdk_process.py); the config and the connect deadline are in sdk_connect.py, and their
names are importable from here too.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from cfknode.kernel.messages import first_line
from cfknode.mocap.sdk_connect import (  # noqa: F401  (re-exported)
    MOCAP_TYPES,
    SDK_TYPES,
    Connector,
    MocapError,
    connect_with_deadline,
    motioncapture_config,
    sdk_label,
)
from cfknode.mocap.sdk_process import (  # noqa: F401  (re-exported)
    SdkQuaternion,
    SdkRigidBody,
    SubprocessMotionCapture,
    default_connector,
)
from cfknode.mocap.source import MocapStats, Pose, RateMeter

# Crazyswarm2 warns when the mocap rate leaves this band (server.yaml; docs/hardware.md#mocap).
RATE_BAND_HZ = (80.0, 120.0)
RATE_CHECK_PERIOD = 1.0  # s between rate checks in the reader thread

_log = logging.getLogger("cfknode.mocap")


@dataclass(frozen=True)
class MocapStatus:
    """What the pre-flight checks and the dashboard need of the stream."""

    frames: int  # frames that held the rigid body
    dropouts: int  # frames without it (occluded or not defined)
    stream_frames: int  # all frames
    stream_rate_hz: float
    body_rate_hz: float
    last_seen_age: float | None  # s since the body was last seen (None: never)
    latest: Pose | None
    error: str | None  # why the stream ended, if it did


class MotioncaptureSource:
    """A ``PoseSource`` reading one rigid body from a ``motioncapture``-like client in a thread.

    ``time_base`` is the flight clock (a ``now()`` callable running at wall-clock rate); until
    it is set, poses are stamped in ``time.monotonic()`` seconds. ``on_pose(pose)`` is called
    in the reader thread for every pose (the hardware radio forwards it as an extpose).
    """

    def __init__(
        self,
        client: Any,
        rigid_body: str,
        *,
        expected_rate_hz: float = 100.0,
        label: str = "mocap",
        on_pose: Callable[[Pose], None] | None = None,
        rate_band: tuple[float, float] = RATE_BAND_HZ,
    ) -> None:
        self._client = client
        self.rigid_body = rigid_body
        self.label = label
        self.expected_rate_hz = expected_rate_hz
        self._rate_band = rate_band
        self._on_pose = on_pose
        self._offset = 0.0  # flight time = monotonic + offset
        self._lock = threading.Lock()
        self._latest: Pose | None = None
        self._latest_mono: float | None = None
        self._frames = 0
        self._dropouts = 0
        self._stream_frames = 0
        self._callback_errors = 0
        self._body_meter = RateMeter(window=1.0)
        self._stream_meter = RateMeter(window=1.0)
        self._error: str | None = None
        self._out_of_band = False
        self.warnings: deque[tuple[float, str]] = deque(maxlen=100)  # (flight time, text)
        self._stop = False
        self._next_check = math.inf
        self._thread = threading.Thread(target=self._run, name=f"mocap-reader {label}", daemon=True)

    @classmethod
    def open(
        cls,
        mocap_type: str,
        host: str,
        rigid_body: str,
        *,
        timeout: float = 5.0,
        connect: Connector | None = None,
        expected_rate_hz: float = 100.0,
        mock_bodies: Mapping[str, tuple[float, ...]] | None = None,
        on_pose: Callable[[Pose], None] | None = None,
    ) -> "MotioncaptureSource":
        """Connect (with a deadline: ``MocapError`` naming the type and host) and start reading."""
        cfg = motioncapture_config(mocap_type, host, mock_bodies=mock_bodies, mock_rate_hz=expected_rate_hz)
        connect = connect if connect is not None else default_connector(timeout)
        client = connect_with_deadline(connect, mocap_type, cfg, timeout)
        return cls(client, rigid_body, expected_rate_hz=expected_rate_hz, label=sdk_label(mocap_type, cfg),
                   on_pose=on_pose).start()

    def start(self) -> "MotioncaptureSource":
        self._thread.start()
        return self

    def set_pose_listener(self, on_pose: Callable[[Pose], None] | None) -> None:
        """Call ``on_pose(pose)`` in the reader thread for every pose from now on."""
        self._on_pose = on_pose

    # --- reader thread ---------------------------------------------------------------------

    def _run(self) -> None:
        client = self._client
        name = self.rigid_body
        while not self._stop:
            try:
                client.waitForNextFrame()
                mono = getattr(client, "frame_monotonic", None) or time.monotonic()
                body = client.rigidBodies.get(name)
            except Exception as exc:
                self.stream_ended(exc)
                return
            self.ingest(mono, body)

    def stream_ended(self, exc: BaseException) -> None:
        """The client failed (or was closed): remember why, in one line, unless we are closing."""
        if not self._stop:
            self._error = first_line(f"{exc}" if isinstance(exc, MocapError) else f"{type(exc).__name__}: {exc}")
            _log.error("%s: %s", self.label, self._error)

    def ingest(self, mono: float, body: Any) -> None:
        """One frame of the stream, received at ``mono``; ``body`` is this rigid body in it (None: missing).
        Called by the reader thread: this source's own, or a shared one (mocap/shared_source.py)."""
        pose = None if body is None else _pose_of(body, mono + self._offset)
        with self._lock:
            self._stream_frames += 1
            self._stream_meter.add(mono)
            if pose is None:
                self._dropouts += 1
            else:
                self._frames += 1
                self._body_meter.add(mono)
                self._latest, self._latest_mono = pose, mono
        if pose is not None and self._on_pose is not None:
            try:
                self._on_pose(pose)
            except Exception:  # a consumer's bug must not stop the stream
                self._callback_errors += 1
        if mono >= self._next_check:
            self._next_check = mono + RATE_CHECK_PERIOD
            self._check_rate(mono)
        elif self._next_check == math.inf:
            self._next_check = mono + RATE_CHECK_PERIOD  # one period after the first frame

    def reader_alive(self) -> bool:
        return self._thread.is_alive()

    def _check_rate(self, mono: float) -> None:
        with self._lock:
            rate = self._body_meter.rate(mono)
        low, high = self._rate_band
        out = not low <= rate <= high
        if out and not self._out_of_band:
            text = f"{self.label}: {self.rigid_body} arrives at {rate:.0f} Hz, outside {low:.0f}-{high:.0f} Hz"
            _log.warning("%s", text)
            self.warnings.append((mono + self._offset, text))
        elif not out and self._out_of_band:
            text = f"{self.label}: {self.rigid_body} back at {rate:.0f} Hz"
            _log.info("%s", text)
            self.warnings.append((mono + self._offset, text))
        self._out_of_band = out

    # --- PoseSource ------------------------------------------------------------------------

    def latest(self, now: float) -> Pose | None:
        # Frames are stamped when they arrive, so every one held is already available.
        return self._latest

    def stats(self) -> MocapStats:
        now = time.monotonic()
        with self._lock:
            return MocapStats(frames=self._frames, dropouts=self._dropouts, rate_hz=self._body_meter.rate(now))

    def status(self) -> MocapStatus:
        now = time.monotonic()
        with self._lock:
            return MocapStatus(
                frames=self._frames,
                dropouts=self._dropouts,
                stream_frames=self._stream_frames,
                stream_rate_hz=self._stream_meter.rate(now),
                body_rate_hz=self._body_meter.rate(now),
                last_seen_age=None if self._latest_mono is None else now - self._latest_mono,
                latest=self._latest,
                error=self._error,
            )

    def set_time_base(self, flight_now: Callable[[], float]) -> None:
        """Stamp poses on the flight clock from now on (and restamp the newest one)."""
        with self._lock:
            self._offset = flight_now() - time.monotonic()
            if self._latest is not None and self._latest_mono is not None:
                old = self._latest
                self._latest = Pose(self._latest_mono + self._offset, old.position, old.quaternion)

    def wait_for_frames(self, n: int, timeout: float) -> bool:
        """Block (never on the event loop) until ``n`` poses of the body have arrived."""
        end = time.monotonic() + timeout
        while self._frames < n and time.monotonic() < end and self._error is None and self.reader_alive():
            time.sleep(0.005)
        return self._frames >= n

    def close(self) -> None:
        self._stop = True
        close_client(self._client, self._thread)


def close_client(client: Any, reader: threading.Thread) -> None:
    """Close an SDK connection its reader thread blocks on, join the reader, then release the client
    (only once the reader is gone: releasing under a blocked read crashes some SDKs)."""
    closer = getattr(client, "close", None)
    if closer is not None:
        closer()
    if reader.is_alive() and reader is not threading.current_thread():
        reader.join(timeout=1.0)
    release = getattr(client, "release", None)
    if release is not None and not reader.is_alive():
        release()


def _pose_of(body: Any, t: float) -> Pose | None:
    """A rigid body's pose, or None when it is not usable (NaN from an SDK, zero quaternion)."""
    p = body.position
    q = body.rotation
    x, y, z = float(p[0]), float(p[1]), float(p[2])
    qw, qx, qy, qz = float(q.w), float(q.x), float(q.y), float(q.z)
    norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if not (math.isfinite(x + y + z) and math.isfinite(norm)) or norm < 0.5:
        return None
    return Pose(t, np.array((x, y, z)), np.array((qw / norm, qx / norm, qy / norm, qz / norm)))
