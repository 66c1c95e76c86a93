"""Reading a fleet flight's log: every drone's channels under its name (``/cf1/state``), docs/fleet.md.

``FleetColumnSink`` keeps the chosen fields of the flight-wide topics and of every drone's
(``/<name>/<topic>`` for each chosen ``/<topic>``, found while streaming); ``DroneColumns`` shows
one drone's part with the plain topic names, so code written for a single flight's
``LogColumns`` (the plots) reads it unchanged; ``drone_log`` does the same for a whole-message
``LogData`` (replay). A single-drone log reads as before.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cfknode.app.logs.data import ColumnSink, LogColumns, LogDamage, LogData

__all__ = ["DroneColumns", "FleetColumnSink", "choose_drones", "drone_log", "fleet_drones"]


def _split(topic: str) -> tuple[str, str] | None:
    """``/cf1/state`` -> ("cf1", "/state"); None for a flight-wide (one-level) topic."""
    parts = topic.split("/")
    if len(parts) != 3 or parts[0] or not parts[1] or not parts[2]:
        return None
    return parts[1], "/" + parts[2]


class FleetColumnSink(ColumnSink):
    """A ``ColumnSink`` that also keeps ``/<drone>/<topic>`` for the chosen topics (of ``drones`` only, if given).

    ``names`` lists every drone seen on such a topic, kept or not.
    """

    def __init__(self, fields: Mapping[str, Sequence[str]], whole: Sequence[str],
                 drones: Collection[str] | None = None) -> None:
        super().__init__(fields, whole)
        self._fields = tuple(fields)
        self._whole = tuple(whole)
        self._drones = None if drones is None else frozenset(drones)
        self._known: set[str] = set()
        self.names: list[str] = []

    def __call__(self, topic: str, msg: dict[str, Any]) -> None:
        if topic not in self._known:  # once per topic: is it a drone's, and wanted?
            self._known.add(topic)
            self._learn(topic)
        super().__call__(topic, msg)

    def _learn(self, topic: str) -> None:
        split = _split(topic)
        if split is None:
            return
        name, base = split
        if base not in self._fields and base not in self._whole:
            return
        if name not in self.names:
            self.names.append(name)
        if self._drones is not None and name not in self._drones:
            return
        self.add_alias(topic, base)

    def whole_topic(self, topic: str) -> bool:
        split = _split(topic)
        return topic in self._whole or (split is not None and split[1] in self._whole)


def fleet_drones(log: LogColumns | LogData) -> list[str]:
    """The drones of a fleet log in flight order ([] for a single drone's log).

    From the logged config (``fleet_drones``), else from the ``/<name>/state`` topics found.
    """
    config = log.config or {}
    listed = config.get("fleet_drones")
    if isinstance(listed, dict) and listed:
        return [str(n) for n in listed]
    if isinstance(log, LogData):
        return list(dict.fromkeys(s[0] for s in map(_split, log.messages) if s is not None and s[1] == "/state"))
    sink = log.sink
    return list(sink.names) if isinstance(sink, FleetColumnSink) else []


def drone_log(log: LogData, name: str) -> LogData:
    """Drone ``name``'s part of a fleet ``LogData`` under single-flight topic names (``/cf1/state`` as ``/state``);
    the flight-wide ``/config`` stays."""
    prefix = f"/{name}/"
    messages = {"/" + topic[len(prefix):]: msgs for topic, msgs in log.messages.items() if topic.startswith(prefix)}
    if "/config" in log.messages:
        messages.setdefault("/config", log.messages["/config"])
    # The drone list is the log's, not a config key: leave it out so the config reads as a flight's.
    config = {k: v for k, v in log.config.items() if k != "fleet_drones"} if log.config is not None else None
    return dataclasses.replace(log, messages=messages, config=config)


def choose_drones(path: str | Path, names: Sequence[str], wanted: Sequence[str] | None) -> list[str]:
    """``wanted`` (all when None) checked against the log's drones; ``ValueError`` (one line) naming them."""
    if wanted is None:
        return list(names)
    unknown = [n for n in wanted if n not in names]
    if unknown:
        raise ValueError(f"{path}: no drone {', '.join(unknown)} in this fleet log; it has {', '.join(names)}")
    return list(dict.fromkeys(wanted))  # in the order asked, once each


class DroneColumns:
    """One drone of a fleet log with single-flight topic names: ``times("/state")`` reads ``/cf1/state``.

    The interface of ``LogColumns`` (``count``, ``times``, ``array``, ``present``, ``topic``,
    ``end_time``, and its attributes); the config is the fleet's.
    """

    def __init__(self, log: LogColumns, name: str) -> None:
        self._log = log
        self.name = name
        self._prefix = f"/{name}"
        self.path: Path = log.path
        self.config: dict[str, Any] | None = log.config
        self.software_version = log.software_version
        self.truncated: bool = log.truncated
        self.note: str = log.note
        self.damage: LogDamage = log.damage

    def _topic(self, topic: str) -> str:
        return self._prefix + topic

    def count(self, topic: str) -> int:
        return self._log.count(self._topic(topic))

    def times(self, topic: str) -> np.ndarray:
        return self._log.times(self._topic(topic)) if self.count(topic) else np.zeros(0)

    def array(self, topic: str, field_name: str) -> np.ndarray:
        return self._log.array(self._topic(topic), field_name)

    def present(self, topic: str, field_name: str) -> int:
        return self._log.present(self._topic(topic), field_name) if self.count(topic) else 0

    def topic(self, name: str) -> list[dict[str, Any]]:
        sink = self._log.sink
        prefixed = self._topic(name)
        if prefixed in sink.whole:
            return sink.whole[prefixed]
        if isinstance(sink, FleetColumnSink) and sink.whole_topic(prefixed):
            return []  # asked for, but this drone wrote none
        raise KeyError(f"topic {prefixed} was not read whole")

    def end_time(self) -> float:
        ends = [t for topic, t in self._log.sink.last_t.items()
                if topic.startswith(self._prefix + "/") and topic != self._topic("/summary")]
        return max(ends) if ends else 0.0
