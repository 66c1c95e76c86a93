"""Foxglove's standard messages for one flight, built from what a tick saw: pure functions.

Each drone is a frame (``FrameTransform`` from ``world`` to the drone's name); the reference path,
the MPC's predicted horizon and the geofence are ``SceneUpdate`` line entities in ``world``;
events are ``Log`` messages. Times are flight times, as everywhere in cfknode's logs, so a log's
3D view and its plots share one time axis. See docs/foxglove.md.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from foxglove.messages import (
    Color,
    FrameTransform,
    LinePrimitive,
    LinePrimitiveLineType,
    Log,
    LogLevel,
    Point3,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    Timestamp,
    Vector3,
)

WORLD = "world"

# Colours: the reference a calm blue, the plan orange (it moves), the fence red and translucent.
REFERENCE_COLOR = (0.20, 0.55, 1.0, 1.0)
HORIZON_COLOR = (1.0, 0.55, 0.0, 1.0)
FENCE_COLOR = (1.0, 0.15, 0.15, 0.6)

_LEVELS = {"debug": LogLevel.Debug, "info": LogLevel.Info, "warning": LogLevel.Warning,
           "error": LogLevel.Error, "fatal": LogLevel.Fatal}


def timestamp(t: float) -> Timestamp:
    """Flight time ``t`` (s, >= 0) as a Foxglove timestamp."""
    ns = max(0, round(t * 1e9))
    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def pose_transform(t: float, frame: str, p: Sequence[float], q_wxyz: Sequence[float]) -> FrameTransform:
    """The drone's pose: ``world`` -> ``frame``, position ``p`` (m), quaternion scalar-first (cfknode's order)."""
    w, x, y, z = (float(c) for c in q_wxyz)
    return FrameTransform(timestamp=timestamp(t), parent_frame_id=WORLD, child_frame_id=frame,
                          translation=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                          rotation=Quaternion(x=x, y=y, z=z, w=w))


def _line(points: np.ndarray, color: tuple[float, float, float, float], thickness: float,
          kind: LinePrimitiveLineType = LinePrimitiveLineType.LineStrip) -> LinePrimitive:
    return LinePrimitive(type=kind, thickness=thickness, scale_invariant=True,
                         points=[Point3(x=float(a), y=float(b), z=float(c)) for a, b, c in points],
                         color=Color(r=color[0], g=color[1], b=color[2], a=color[3]))


def path_entity(t: float, entity_id: str, points: np.ndarray, color: tuple[float, float, float, float],
                thickness: float = 2.0) -> SceneEntity:
    """A polyline through ``points`` (n, 3) in ``world``, replacing any earlier entity of the same id."""
    return SceneEntity(timestamp=timestamp(t), frame_id=WORLD, id=entity_id,
                       lines=[_line(np.asarray(points, dtype=float).reshape(-1, 3), color, thickness)])


def box_edges(low: Sequence[float], high: Sequence[float]) -> np.ndarray:
    """The 12 edges of an axis-aligned box as 24 points (pairs), for a line list."""
    lo, hi = np.asarray(low, dtype=float), np.asarray(high, dtype=float)
    corners = np.array([[hi[0] if i & 1 else lo[0], hi[1] if i & 2 else lo[1], hi[2] if i & 4 else lo[2]]
                        for i in range(8)])
    # Two corners share an edge when their indices differ in exactly one bit.
    pairs = [(i, i | bit) for i in range(8) for bit in (1, 2, 4) if not i & bit]
    return np.array([corners[k] for pair in pairs for k in pair])


def fence_entity(t: float, low: Sequence[float], high: Sequence[float]) -> SceneEntity:
    """The geofence's box as a wireframe."""
    line = _line(box_edges(low, high), FENCE_COLOR, 1.5, LinePrimitiveLineType.LineList)
    return SceneEntity(timestamp=timestamp(t), frame_id=WORLD, id="fence", lines=[line])


def scene(entities: Sequence[SceneEntity]) -> SceneUpdate:
    return SceneUpdate(entities=list(entities))


def log_message(t: float, level: str, text: str, source: str = "cfknode") -> Log:
    """An event as a Foxglove log line (an unknown level is shown as info)."""
    return Log(timestamp=timestamp(t), level=_LEVELS.get(level, LogLevel.Info), message=text, name=source)
