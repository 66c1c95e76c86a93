"""The simulator as a ``motioncapture`` client: every simulated body in each frame, as a real mocap serves them.

``SimulatedMotionCaptureClient`` offers the object API the reader thread uses
(``waitForNextFrame``, ``rigidBodies``) over one ``SimulatedMocap`` per body (frame rate,
noise, latency, dropouts), for simulators stepping in another thread. A dropped frame of a
body arrives without that body, as an occluded Vicon subject does. With several bodies (a
fleet in one ``SimWorld``) the frame is published from the step observer of the body
stepped last, so every body has been sampled at that instant.
"""

from __future__ import annotations

import threading
from typing import Any, Mapping

import numpy as np

from cfknode.mocap.motioncapture_source import MocapError, SdkQuaternion, SdkRigidBody
from cfknode.mocap.simulated import SimulatedMocap


class SimulatedMotionCaptureClient:
    """``bodies``: rigid-body name -> simulator (in the order the world steps them)."""

    def __init__(
        self, bodies: Mapping[str, Any], *, rate_hz: float, position_noise: float = 0.0,
        attitude_noise: float = 0.0, latency: float = 0.0, dropout_prob: float = 0.0, seed: int = 0,
    ) -> None:
        if not bodies:
            raise ValueError("a simulated mocap needs at least one body")
        self._sims = dict(bodies)
        # Each body its own noise stream (seed + i), so two robots' errors are independent.
        self._sources = {name: SimulatedMocap(sim, rate_hz, position_noise, attitude_noise, latency, dropout_prob,
                                              seed + i)
                         for i, (name, sim) in enumerate(self._sims.items())}
        self._cond = threading.Condition()
        self._seq = 0
        self._consumed = 0
        self._last_pose: dict[str, Any] = {name: None for name in self._sims}  # the newest pose delivered
        self._last_dropouts = {name: 0 for name in self._sims}
        self._ready: dict[str, SdkRigidBody] = {}
        self._bodies: dict[str, SdkRigidBody] = {}
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
            self._ready = frame
            self._seq += 1
            self._cond.notify_all()

    def waitForNextFrame(self) -> None:  # noqa: N802 (the SDK's name)
        with self._cond:
            self._cond.wait_for(lambda: self._seq > self._consumed or self._closed)
            if self._closed:
                raise MocapError("simulated mocap closed")
            self._consumed = self._seq
            self._bodies = self._ready

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
