"""Hardware mocap through libmotioncapture (``motioncapture`` on PyPI): vicon, optitrack, qualisys, vrpn.

A reader thread calls ``waitForNextFrame()`` and turns the rigid body named like the robot
into a ``Pose`` stamped with the host's monotonic clock when the frame arrived (the Python
bindings expose no SDK timestamp: docs/hardware.md#mocap), shifted onto the flight clock. A frame without
the body (occluded: the SDKs silently omit it) counts as a dropout. The quaternion comes as
``.w .x .y .z`` attributes and is stored scalar-first.

Two blocking calls need care:

- ``motioncapture.connect`` loops forever when a Vicon or OptiTrack host is silent, and it
  holds the GIL while it does (measured here: the interpreter froze), so a thread with a
  deadline cannot even wake up to give up. The SDK types therefore run in a child process
  (``SubprocessMotionCapture``) that sends frames over a pipe; the parent waits with a
  deadline and kills the child if the host never answers. A side benefit: Vicon's
  ``waitForNextFrame`` busy-spins, and now it does so on another core's GIL.
- ``waitForNextFrame`` blocks until the next frame; it runs in the reader thread only.

``connect`` is injectable (``(type, cfg) -> object with waitForNextFrame() and rigidBodies``),
so tests drive the same reader thread with a fake fed by the simulator.
"""

from __future__ import annotations

import json
import logging
import math
import os
import select
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from cfknode.mocap.source import MocapStats, Pose, RateMeter

MOCAP_TYPES = ("vicon", "optitrack", "qualisys", "vrpn", "mock")
SDK_TYPES = ("vicon", "optitrack", "qualisys", "vrpn")
# Crazyswarm2 warns when the mocap rate leaves this band (server.yaml; docs/hardware.md#mocap).
RATE_BAND_HZ = (80.0, 120.0)
RATE_CHECK_PERIOD = 1.0  # s between rate checks in the reader thread
_WAIT_POLL = 0.2  # s: how often a blocked wait on the child pipe looks at the stop flag

Connector = Callable[[str, dict[str, str]], Any]
_log = logging.getLogger("cfknode.mocap")


class MocapError(RuntimeError):
    """The mocap could not connect or its stream ended; the message is one line."""


def motioncapture_config(
    mocap_type: str, host: str, *, mock_bodies: Mapping[str, tuple[float, ...]] | None = None,
    mock_rate_hz: float = 100.0,
) -> dict[str, str]:
    """The string dict ``motioncapture.connect`` takes (``src/motioncapture.cpp`` keys; docs/hardware.md#mocap).

    ``host`` may carry a port (``vicon``: ``host:801``, the SDK parses it; ``qualisys``: it
    becomes the ``port`` key). ``mock`` ignores the host and serves ``mock_bodies``
    (name -> x, y, z, qw, qx, qy, qz) as static frames at ``mock_rate_hz``.
    """
    if mocap_type not in MOCAP_TYPES:
        raise MocapError(f"unknown mocap type {mocap_type!r}; use one of {', '.join(MOCAP_TYPES)}")
    if mocap_type == "mock":
        bodies = ";".join(
            f"{name}({','.join(format(float(v), '.9g') for v in values)})"
            for name, values in (mock_bodies or {}).items()
        )
        return {"rigid_bodies": bodies, "frequency": format(float(mock_rate_hz), "g")}
    if not host:
        raise MocapError(f"{mocap_type} needs a host (hardware.mocap_host / --mocap-host)")
    if mocap_type == "qualisys" and ":" in host:
        hostname, port = host.rsplit(":", 1)
        return {"hostname": hostname, "port": port}
    return {"hostname": host}


# --- the SDK in a child process --------------------------------------------------------------
#
# The child is ``python -m cfknode.mocap.motioncapture_source TYPE CFG_JSON`` (not multiprocessing:
# spawn re-imports the caller's main module, which breaks scripts without a main guard). It
# writes one JSON line per message on stdout: {"connected": true}, {"error": "..."} or
# {"t": monotonic seconds, "b": [[name, x, y, z, qw, qx, qy, qz], ...]}.


def _die_with_parent() -> None:
    """Linux: the child gets SIGKILL when the parent dies, even while stuck inside the SDK."""
    try:
        import ctypes
        import signal

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGKILL)
    except (OSError, AttributeError):
        pass


def _child_main(mocap_type: str, cfg: dict[str, str], out: Any) -> None:
    """Child process: connect, then write (monotonic time, bodies) for every frame."""
    _die_with_parent()

    def send(msg: dict[str, Any]) -> bool:
        try:
            out.write(json.dumps(msg, separators=(",", ":")).encode() + b"\n")
            out.flush()
            return True
        except (OSError, ValueError):  # the parent closed the pipe or died
            return False

    try:
        import motioncapture

        mc = motioncapture.connect(mocap_type, cfg)
    except Exception as exc:  # the SDK's RuntimeError: say it in one line to the parent
        send({"error": f"{type(exc).__name__}: {exc}"})
        return
    if not send({"connected": True}):
        return
    while True:
        try:
            mc.waitForNextFrame()
            t = time.monotonic()  # CLOCK_MONOTONIC is system-wide: comparable in the parent
            bodies = []
            for name, rb in mc.rigidBodies.items():
                p, q = rb.position, rb.rotation
                bodies.append([name, float(p[0]), float(p[1]), float(p[2]), q.w, q.x, q.y, q.z])
        except Exception as exc:
            send({"error": f"{type(exc).__name__}: {exc}"})
            return
        if not send({"t": t, "b": bodies}):
            return


@dataclass(frozen=True)
class SdkQuaternion:
    """A quaternion shaped like motioncapture's (``.w .x .y .z``), for stand-ins of the SDK."""

    w: float
    x: float
    y: float
    z: float


@dataclass(frozen=True)
class SdkRigidBody:
    """A rigid body shaped like motioncapture's (``.name .position .rotation``)."""

    name: str
    position: Any  # 3 floats, meters (the SDK gives a float32 array)
    rotation: SdkQuaternion


class SubprocessMotionCapture:
    """The ``motioncapture`` object's API (``waitForNextFrame``, ``rigidBodies``), served by a
    child process; ``frame_monotonic`` is when the child received the current frame."""

    def __init__(self, mocap_type: str, cfg: Mapping[str, str], timeout: float) -> None:
        self.mocap_type = mocap_type
        self.cfg = dict(cfg)
        self._proc = subprocess.Popen(
            [sys.executable, "-m", __name__, mocap_type, json.dumps(self.cfg)],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
        )
        self._fd = self._proc.stdout.fileno()
        self._buffer = b""
        self._bodies: dict[str, SdkRigidBody] = {}
        self.frame_monotonic: float | None = None
        self._closed = False
        try:
            msg = self._next_message(timeout)
            if msg is None:
                raise MocapError(_no_answer(mocap_type, self.cfg, timeout))
            if "error" in msg:
                raise MocapError(f"could not connect to {_label(mocap_type, self.cfg)}: {_first_line(msg['error'])}")
        except BaseException:
            self.release()
            raise

    def _next_message(self, timeout: float) -> dict[str, Any] | None:
        """The next JSON line, or None after ``timeout`` s; ``MocapError`` when the child is gone."""
        end = time.monotonic() + timeout
        while b"\n" not in self._buffer:
            left = end - time.monotonic()
            if left <= 0 or self._closed:
                return None
            ready, _, _ = select.select([self._fd], [], [], min(left, _WAIT_POLL))
            if not ready:
                continue
            chunk = os.read(self._fd, 65536)
            if not chunk:
                raise MocapError(f"{_label(self.mocap_type, self.cfg)}: the mocap client process ended")
            self._buffer += chunk
        line, _, self._buffer = self._buffer.partition(b"\n")
        return json.loads(line)

    def waitForNextFrame(self) -> None:  # noqa: N802 (the SDK's name)
        while True:
            if self._closed:
                raise MocapError("mocap client closed")
            msg = self._next_message(_WAIT_POLL)
            if msg is None:
                continue
            if "error" in msg:
                raise MocapError(f"{_label(self.mocap_type, self.cfg)}: {_first_line(msg['error'])}")
            if "t" in msg:
                break
        self.frame_monotonic = float(msg["t"])
        self._bodies = {
            b[0]: SdkRigidBody(b[0], (b[1], b[2], b[3]), SdkQuaternion(b[4], b[5], b[6], b[7])) for b in msg["b"]
        }

    @property
    def rigidBodies(self) -> dict[str, SdkRigidBody]:  # noqa: N802 (the SDK's name)
        return self._bodies

    def close(self) -> None:
        """Stop the child; a reader blocked in ``waitForNextFrame`` sees the end of the pipe."""
        self._closed = True
        proc = self._proc
        if proc.poll() is None:
            proc.kill()  # the SDK may be stuck in C++ holding the child's GIL: no polite way out
        try:
            proc.wait(1.0)
        except subprocess.TimeoutExpired:
            pass

    def release(self) -> None:
        """Close the pipe, once no thread reads it any more."""
        self.close()
        if self._proc.stdout is not None:
            self._proc.stdout.close()


def default_connector(timeout: float) -> Connector:
    """How cfknode connects: SDK types in a child process (connect may hang holding the GIL),
    ``mock`` in-process (it returns at once and its waits release the GIL)."""

    def connect(mocap_type: str, cfg: dict[str, str]) -> Any:
        if mocap_type in SDK_TYPES:
            return SubprocessMotionCapture(mocap_type, cfg, timeout)
        import motioncapture

        return motioncapture.connect(mocap_type, cfg)

    return connect


def connect_with_deadline(connect: Connector, mocap_type: str, cfg: dict[str, str], timeout: float) -> Any:
    """Run ``connect`` in a thread and give up after ``timeout`` with a one-line error."""
    result: dict[str, Any] = {}
    lock = threading.Lock()

    def run() -> None:
        try:
            client = connect(mocap_type, cfg)
        except BaseException as exc:  # handed to the caller's thread
            result["error"] = exc
            return
        with lock:
            abandoned = result.get("abandoned", False)
            result["client"] = client
        if abandoned:  # answered after the caller gave up: nobody will read it
            closer = getattr(client, "release", None) or getattr(client, "close", None)
            if closer is not None:
                closer()

    thread = threading.Thread(target=run, name=f"mocap-connect {mocap_type}", daemon=True)
    thread.start()
    thread.join(timeout)
    with lock:
        if "client" not in result and "error" not in result:
            result["abandoned"] = True
            raise MocapError(_no_answer(mocap_type, cfg, timeout))
    error = result.get("error")
    if isinstance(error, MocapError):
        raise error
    if error is not None:
        raise MocapError(f"could not connect to {_label(mocap_type, cfg)}: "
                         f"{_first_line(f'{type(error).__name__}: {error}')}") from None
    return result["client"]


def _label(mocap_type: str, cfg: Mapping[str, str]) -> str:
    host = cfg.get("hostname")
    if host and cfg.get("port"):
        host = f"{host}:{cfg['port']}"
    return f"{mocap_type} at {host}" if host else mocap_type


def _no_answer(mocap_type: str, cfg: Mapping[str, str], timeout: float) -> str:
    return (f"no answer from {_label(mocap_type, cfg)} within {timeout:g} s "
            "(is the mocap software running and streaming, and is the host right?)")


def _first_line(message: str) -> str:
    lines = [line.strip() for line in str(message).splitlines() if line.strip()]
    return lines[0] if lines else "unknown error"


# --- the pose source -------------------------------------------------------------------------


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
        return cls(client, rigid_body, expected_rate_hz=expected_rate_hz, label=_label(mocap_type, cfg),
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
        next_check = math.inf  # one period after the first frame
        while not self._stop:
            try:
                client.waitForNextFrame()
                mono = getattr(client, "frame_monotonic", None) or time.monotonic()
                body = client.rigidBodies.get(name)
            except Exception as exc:
                if not self._stop:
                    self._error = _first_line(f"{exc}" if isinstance(exc, MocapError) else f"{type(exc).__name__}: {exc}")
                    _log.error("%s: %s", self.label, self._error)
                return
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
            if mono >= next_check:
                next_check = mono + RATE_CHECK_PERIOD
                self._check_rate(mono)
            elif next_check == math.inf:
                next_check = mono + RATE_CHECK_PERIOD

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
        while self._frames < n and time.monotonic() < end and self._error is None and self._thread.is_alive():
            time.sleep(0.005)
        return self._frames >= n

    def close(self) -> None:
        self._stop = True
        closer = getattr(self._client, "close", None)
        if closer is not None:
            closer()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        release = getattr(self._client, "release", None)
        if release is not None and not self._thread.is_alive():
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


if __name__ == "__main__":
    _child_main(sys.argv[1], json.loads(sys.argv[2]), sys.stdout.buffer)
