"""The simulator as a ``motioncapture`` client: every simulated body in each frame, as a real mocap serves them.

``SimulatedMotionCaptureClient`` offers the object API the reader thread uses
(``waitForNextFrame``, ``rigidBodies``) over one ``SimulatedMocap`` per body (frame rate,
noise, latency, dropouts), for simulators stepping in another thread. A dropped frame of a
body arrives without that body, as an occluded Vicon subject does. With several bodies (a
fleet in one ``SimWorld``) the frame is published from the step observer of the body
stepped last, so every body has been sampled at that instant.

Frames reach the reader as the SDK's child process hands them over on hardware
(mocap/sdk_process.py): every frame, in order, stamped (``frame_monotonic``) when the
simulated system sent it. A simulator that falls behind the wall clock on a loaded machine and
catches up sends its late frames at once; stamped on arrival they read as a burst (a pre-flight
measured 164 Hz of a 100 Hz stream), stamped when sent they keep the stream's rate.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Any, Callable, Mapping

import numpy as np

from cfknode.mocap.motioncapture_source import MocapError, SdkQuaternion, SdkRigidBody
from cfknode.mocap.simulated import SimulatedMocap


MAX_UNREAD_FRAMES = 1000  # 10 s at 100 Hz


class SimulatedMotionCaptureClient:
    """``bodies``: rigid-body name -> simulator (in the order the world steps them); ``frame_time``:
    the ``time.monotonic()`` of a simulator time (None: frames carry no stamp, the reader's clock
    stamps them on arrival)."""

    def __init__(
        self, bodies: Mapping[str, Any], *, rate_hz: float, position_noise: float = 0.0,
        attitude_noise: float = 0.0, latency: float = 0.0, dropout_prob: float = 0.0, seed: int = 0,
        frame_time: Callable[[float], float] | None = None,
    ) -> None:
        if not bodies:
            raise ValueError("a simulated mocap needs at least one body")
        self._sims = dict(bodies)
        # Each body its own noise stream (seed + i), so two robots' errors are independent.
        self._sources = {name: SimulatedMocap(sim, rate_hz, position_noise, attitude_noise, latency, dropout_prob,
                                              seed + i)
                         for i, (name, sim) in enumerate(self._sims.items())}
        self._frame_time = frame_time
        self._cond = threading.Condition()
        self._last_pose: dict[str, Any] = {name: None for name in self._sims}  # the newest pose delivered
        self._last_dropouts = {name: 0 for name in self._sims}
        # Sent, not yet read: bounded as a pipe is (a reader that stops reading loses the oldest).
        self._ready: deque[tuple[float, dict[str, SdkRigidBody]]] = deque(maxlen=MAX_UNREAD_FRAMES)
        self._bodies: dict[str, SdkRigidBody] = {}
        self.frame_monotonic: float | None = None  # when the frame being read was sent
        self._closed = False
        self._observed = list(self._sims.values())[-1]
        # After the sources' own observers: this step's frames are sampled.
        self._observed.add_step_observer(self._on_step)

    def _on_step(self, t: float, state: np.ndarray) -> None:
        if self._closed:
            return
        frame: dict[str, SdkRigidBody] = {}
        changed = False
        for name, source in self._sources.items():
            pose, dropouts = source.latest(t), source.stats().dropouts
            new_pose = pose is not None and pose is not self._last_pose[name]
            changed = changed or new_pose or dropouts != self._last_dropouts[name]
            if new_pose:
                w, x, y, z = (float(c) for c in pose.quaternion)
                frame[name] = SdkRigidBody(name, pose.position.astype(np.float32), SdkQuaternion(w, x, y, z))
            self._last_pose[name], self._last_dropouts[name] = pose, dropouts
        if not changed:
            return
        with self._cond:
            self._ready.append((t, frame))
            self._cond.notify_all()

    def waitForNextFrame(self) -> None:  # noqa: N802 (the SDK's name)
        with self._cond:
            self._cond.wait_for(lambda: self._ready or self._closed)
            if self._closed:
                raise MocapError("simulated mocap closed")
            t, self._bodies = self._ready.popleft()
            self.frame_monotonic = None if self._frame_time is None else self._frame_time(t)

    @property
    def rigidBodies(self) -> dict[str, SdkRigidBody]:  # noqa: N802 (the SDK's name)
        return self._bodies

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        for source in self._sources.values():
            source.close()
        remove = getattr(self._observed, "remove_step_observer", None)
        if remove is not None:
            remove(self._on_step)


__all__ = ["SimulatedMotionCaptureClient"]
