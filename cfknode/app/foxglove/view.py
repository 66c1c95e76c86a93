"""A flight seen in Foxglove: a tap on the flight log that mirrors it in Foxglove's standard schemas.

``FoxgloveView`` wraps the log the loop writes to (it has the same ``write(topic, t, msg)``):
every message goes on to the log unchanged, and a few become Foxglove messages for its sinks:

- ``/state``: the drone's pose as a ``FrameTransform`` on ``/tf`` (every ``pose_every``-th),
  and the MPC's predicted horizon as a ``SceneUpdate`` on ``/scene`` (every ``plan_every``-th);
- ``/events``: a ``Log`` on ``/log``.

The reference path and the geofence go on ``/scene`` at the first state and again every
``static_every_s`` of flight time, so a live viewer that connects late still draws them; they
are encoded once, before take-off (a 700-point path takes about 2 ms to build, too long for a tick).
A fleet's log names each drone's topics ``/<name>/state``: the drone's frame is ``<name>``.
Sinks (``McapSink`` into the flight's MCAP file, ``LiveServer`` to a WebSocket client) take
``publish(topic, t, data)`` with the message encoded in its topic's schema (``SCHEMAS``).
See docs/foxglove.md.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from foxglove.messages import FrameTransform, Log, SceneUpdate

from cfknode.app.foxglove import scene

TF_TOPIC, SCENE_TOPIC, LOG_TOPIC = "/tf", "/scene", "/log"
SCHEMAS = {TF_TOPIC: FrameTransform.get_schema(), SCENE_TOPIC: SceneUpdate.get_schema(), LOG_TOPIC: Log.get_schema()}


class Sink(Protocol):
    def publish(self, topic: str, t: float, data: bytes) -> None: ...


@dataclass(frozen=True)
class Drawing:
    """What one drone's view draws besides its pose and plan: its reference path and the fence."""

    reference: np.ndarray  # (n, 3) m: the whole reference path, sampled
    fence: tuple[Sequence[float], Sequence[float]] | None = None  # the hard box's (low, high) corners


@dataclass(frozen=True)
class ViewRates:
    """Ticks between poses and between plans (400 Hz loop: 50 Hz and 10 Hz), and s between static redraws."""

    pose_every: int = 8
    plan_every: int = 40
    static_every_s: float = 1.0


class FoxgloveView:
    """A log tap that mirrors the flight on Foxglove's ``/tf``, ``/scene`` and ``/log``."""

    def __init__(self, inner: Any, sinks: Sequence[Sink], drawings: Mapping[str, Drawing],
                 rates: ViewRates = ViewRates()) -> None:
        self._inner = inner
        self._sinks = tuple(sinks)
        self._drawings = dict(drawings)  # frame name ("cf" for one drone, the drone's name in a fleet)
        self._rates = rates
        self._count = dict.fromkeys(self._drawings, 0)
        self._static_due = dict.fromkeys(self._drawings, 0.0)
        self._plans: dict[str, Callable[[], np.ndarray | None]] = {}
        self.failures: list[str] = []  # sinks dropped after an error, and why
        self._static = {frame: scene.scene(self._static_entities(frame, d)).encode() for frame, d in drawings.items()}

    def follow_plan(self, frame: str, plan: Callable[[], np.ndarray | None]) -> None:
        """Draw ``plan()`` (the predicted positions, (N+1, 3), or None) as ``frame``'s horizon.

        Set once the controller exists, which is after the log it writes to."""
        self._plans[frame] = plan

    def write(self, topic: str, t: float, msg: Mapping[str, Any]) -> None:
        self._inner.write(topic, t, msg)
        frame, _, leaf = topic.rpartition("/")
        if leaf == "state":
            self._on_state(frame.strip("/") or next(iter(self._drawings)), t, msg)
        elif leaf == "events":
            self._emit(LOG_TOPIC, t, scene.log_message(t, str(msg.get("level", "info")), str(msg.get("text", "")),
                                                       str(msg.get("source", "cfknode"))))

    def _on_state(self, frame: str, t: float, msg: Mapping[str, Any]) -> None:
        drawing = self._drawings.get(frame)
        if drawing is None:
            return
        k = self._count[frame]
        self._count[frame] = k + 1
        if t >= self._static_due[frame]:
            self._static_due[frame] = t + self._rates.static_every_s
            self._emit(SCENE_TOPIC, t, self._static[frame])
        if k % self._rates.pose_every == 0:
            self._emit(TF_TOPIC, t, scene.pose_transform(t, frame, msg["p"], msg["q"]))
        if k % self._rates.plan_every == 0:
            plan = self._plans[frame]() if frame in self._plans else None
            if plan is not None:
                self._emit(SCENE_TOPIC, t, scene.scene(
                    [scene.path_entity(t, f"{frame}/horizon", plan, scene.HORIZON_COLOR, 3.0)]))

    @staticmethod
    def _static_entities(frame: str, drawing: Drawing) -> list[Any]:
        # Stamped 0 with no lifetime: they stand until replaced, whenever a viewer joins.
        entities = [scene.path_entity(0.0, f"{frame}/reference", drawing.reference, scene.REFERENCE_COLOR)]
        if drawing.fence is not None:
            entities.append(scene.fence_entity(0.0, *drawing.fence))
        return entities

    def _emit(self, topic: str, t: float, message: Any) -> None:
        data = message if isinstance(message, bytes) else message.encode()
        for sink in self._sinks:
            try:
                sink.publish(topic, t, data)
            except Exception as exc:  # noqa: BLE001 - a viewer must never end a flight, nor the log's writes
                # Dropped for the rest of the flight, and said once in the summary (``failures``).
                self._sinks = tuple(s for s in self._sinks if s is not sink)
                self.failures.append(f"{type(sink).__name__}: {str(exc)[:120]}")

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)  # path, flush, ...: the wrapped log's


class McapSink:
    """Writes Foxglove messages into the flight's MCAP file, protobuf-encoded with the SDK's schemas."""

    def __init__(self, flight_log: Any) -> None:
        self._log = flight_log
        for topic, schema in SCHEMAS.items():
            flight_log.add_encoded_channel(topic, schema.name, schema.encoding, bytes(schema.data), "protobuf")

    def publish(self, topic: str, t: float, data: bytes) -> None:
        self._log.write_encoded(topic, t, data)


def reference_points(trajectory: Any, step_s: float = 0.05) -> np.ndarray:
    """The trajectory's positions every ``step_s`` from take-off to the end of the landing, (n, 3)."""
    t = np.arange(0.0, float(trajectory.duration) + step_s, step_s)
    return np.asarray(trajectory.sample(t).p, dtype=float)
