"""The mocap SDK in a child process: ``motioncapture.connect`` can hang holding the GIL.

``motioncapture.connect`` loops forever when a Vicon or OptiTrack host is silent, and it
holds the GIL while it does (measured here: the interpreter froze), so a thread with a
deadline cannot even wake up to give up. The SDK types therefore run in a child process
(``SubprocessMotionCapture``) that sends frames over a pipe; the parent waits with a
deadline and kills the child if the host never answers. A side benefit: Vicon's
``waitForNextFrame`` busy-spins, and now it does so on another core's GIL.
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import time
from dataclasses import dataclass
from typing import Any, Mapping

from cfknode.kernel.messages import first_line
from cfknode.mocap.sdk_connect import SDK_TYPES, Connector, MocapError, no_answer, sdk_label

_WAIT_POLL = 0.2  # s: how often a blocked wait on the child pipe looks at the stop flag

# The child is ``python -m cfknode.mocap.sdk_process TYPE CFG_JSON`` (not multiprocessing:
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
                raise MocapError(no_answer(mocap_type, self.cfg, timeout))
            if "error" in msg:
                raise MocapError(f"could not connect to {sdk_label(mocap_type, self.cfg)}: {first_line(msg['error'])}")
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
                raise MocapError(f"{sdk_label(self.mocap_type, self.cfg)}: the mocap client process ended")
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
                raise MocapError(f"{sdk_label(self.mocap_type, self.cfg)}: {first_line(msg['error'])}")
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


if __name__ == "__main__":
    _child_main(sys.argv[1], json.loads(sys.argv[2]), sys.stdout.buffer)
