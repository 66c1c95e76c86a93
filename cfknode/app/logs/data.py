"""What reading a flight log gives: ``LogData`` (every message), ``LogColumns`` (chosen fields as
arrays, for long flights) and ``LogDamage`` (what could not be read, and from when data is missing).

The readers that fill them are in ``logreader``.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cfknode.app.logs.format import CHANNELS, LogError

__all__ = ["ColumnSink", "LogColumns", "LogDamage", "LogData", "require_messages"]


@dataclass(frozen=True)
class LogDamage:
    """What the reader skipped in one log, and from which flight time recorded data is missing."""

    skipped_records: int = 0  # complete but unreadable records (a chunk failing its CRC is one)
    skipped_bytes: int = 0  # their bytes, plus the tail
    tail_bytes: int = 0  # bytes after the last readable record that are not a footer (a cut record)
    gaps: tuple[tuple[float, float], ...] = ()  # flight-time spans (s) of the unreadable chunks
    truncated: bool = False  # no footer: the writer never closed the file
    end_t: float | None = None  # the last flight time read, s
    stopped: str = ""  # why reading ended before the footer, with the byte offset ("" if it did not)
    bad_messages: Mapping[str, int] = field(default_factory=dict)  # "topic: what is wrong" -> count
    warnings: tuple[str, ...] = ()  # problems worked around (a schema or metadata that is not JSON)

    @property
    def bad_message_count(self) -> int:
        return sum(self.bad_messages.values())

    def bad_on(self, topic: str) -> int:
        return sum(n for key, n in self.bad_messages.items() if key.split(":", 1)[0] == topic)

    @property
    def missing_from(self) -> float | None:
        """The earliest flight time (s) from which recorded messages may be missing; None if none are."""
        starts = [t0 for t0, _ in self.gaps]
        if self.truncated and self.end_t is not None:
            starts.append(self.end_t)
        return min(starts) if starts else None

    @property
    def clean(self) -> bool:
        return not (self.skipped_records or self.skipped_bytes or self.truncated or self.bad_messages
                    or self.warnings)

    def line(self) -> str:
        """One line saying what was skipped and what is missing ("" for a clean log)."""
        parts: list[str] = []
        if self.skipped_records:
            spans = ", ".join(f"{a:.2f}-{b:.2f} s" for a, b in self.gaps[:3]) + (", ..." if len(self.gaps) > 3 else "")
            parts.append(f"{self.skipped_records} unreadable record(s) skipped ({self.skipped_bytes - self.tail_bytes}"
                         " bytes)" + (f": flight time {spans} missing" if self.gaps else ""))
        if self.truncated:
            end = f"t = {self.end_t:.2f} s" if self.end_t is not None else "its start"
            parts.append(f"cut short ({self.stopped or 'no footer'}): nothing after {end}")
        if self.bad_messages:
            top = sorted(self.bad_messages.items(), key=lambda kv: -kv[1])
            what = "; ".join(f"{k} x{n}" for k, n in top[:3]) + ("; ..." if len(top) > 3 else "")
            parts.append(f"{self.bad_message_count} malformed message(s) skipped ({what})")
        parts.extend(self.warnings)
        return "; ".join(parts)

    def to_dict(self) -> dict[str, Any]:
        """For ``--json`` output (plain JSON types)."""
        return {
            "clean": self.clean,
            "truncated": self.truncated,
            "skipped_records": self.skipped_records,
            "skipped_bytes": self.skipped_bytes,
            "tail_bytes": self.tail_bytes,
            "missing_from_s": self.missing_from,
            "end_s": self.end_t,
            "gaps_s": [list(g) for g in self.gaps],
            "malformed_messages": dict(self.bad_messages),
            "warnings": list(self.warnings),
            "text": self.line(),
        }


def require_messages(log: LogData | LogColumns, topics: Sequence[str]) -> None:
    """Raise ``LogError`` when a topic the caller needs lost every message to damage (one line)."""
    for topic in topics:
        bad = log.damage.bad_on(topic)
        if bad and log.count(topic) == 0:
            reasons = sorted(k.split(": ", 1)[1] for k in log.damage.bad_messages if k.split(":", 1)[0] == topic)
            raise LogError(f"{log.path}: no usable {topic} messages: all {bad} are malformed "
                           f"({', '.join(reasons[:3])})")


@dataclass(frozen=True)
class LogData:
    """A flight log read back: messages per topic (dicts, as written plus ``t``), config, version.

    ``truncated`` is True when the file has no MCAP footer (the writer never closed it);
    ``note`` says what was skipped or missing (``damage.line()``), or is "".
    Holds every message: for long flights prefer ``logreader.read_columns``.
    """

    path: Path
    messages: Mapping[str, list[dict[str, Any]]]
    config: dict[str, Any] | None
    software_version: str | None
    metadata: Mapping[str, Mapping[str, str]]
    schemas: Mapping[str, Mapping[str, Any]]
    truncated: bool
    note: str = ""
    damage: LogDamage = field(default_factory=LogDamage)

    @property
    def topics(self) -> list[str]:
        return list(self.messages)

    def topic(self, name: str) -> list[dict[str, Any]]:
        """Messages of ``name`` in file order ([] if the topic has none)."""
        return self.messages.get(name, [])

    def count(self, topic: str) -> int:
        return len(self.topic(topic))

    def present(self, topic: str, field_name: str) -> int:
        """How many messages of ``topic`` carry ``field_name``."""
        return sum(field_name in m for m in self.topic(topic))

    def end_time(self) -> float:
        """The last flight time of any topic but ``/summary`` (0 if none)."""
        ends = [float(m[-1]["t"]) for name, m in self.messages.items() if m and name != "/summary"]
        return max(ends) if ends else 0.0

    def times(self, topic: str) -> np.ndarray:
        return np.array([m["t"] for m in self.topic(topic)], dtype=float)

    def array(self, topic: str, field_name: str) -> np.ndarray:
        """One field of every message of ``topic`` as an array: (n,) for scalars, (n, k) for vectors.

        Numbers: float, with NaN for null and for messages lacking the field. Booleans: bool
        (all messages must have the field). Strings: an object array.
        """
        msgs = self.topic(topic)
        values = [m.get(field_name) for m in msgs]
        present = [v for v in values if v is not None]
        if msgs and not present and not any(field_name in m for m in msgs):
            raise KeyError(f"{self.path.name}: no field {field_name!r} on {topic}")
        if present and all(isinstance(v, bool) for v in present):
            if len(present) != len(values):
                raise ValueError(f"{self.path.name}: boolean field {field_name!r} on {topic} has gaps")
            return np.array(values, dtype=bool)
        if present and isinstance(present[0], str):
            return np.array(values, dtype=object)
        width = len(present[0]) if present and isinstance(present[0], list) else None
        if width is None:
            return np.array([np.nan if v is None else v for v in values], dtype=float).reshape(len(values))
        gap = [None] * width
        rows = [gap if v is None else [np.nan if x is None else x for x in v] for v in values]
        return np.array(rows, dtype=float).reshape(len(values), width)


class _Column:
    """One registry field of one topic, appended per message into a compact typed array."""

    def __init__(self, kind: str, width: int) -> None:
        self.kind, self.width = kind, width  # kind: number | boolean | string; width 0: scalar
        self.values = array({"number": "d", "boolean": "b"}.get(kind, "i"))
        self.codes: dict[str, int] = {}  # strings: each distinct value once (sources, states)
        self.present = 0

    def add(self, value: Any) -> None:
        if value is not None:
            self.present += 1
        if self.kind == "number":
            if self.width == 0:
                self.values.append(math.nan if value is None else value)
            elif value is None:
                self.values.extend([math.nan] * self.width)
            else:
                self.values.extend([math.nan if x is None else x for x in value])
        elif self.kind == "boolean":
            self.values.append(-1 if value is None else int(value))
        else:
            self.values.append(-1 if value is None else self.codes.setdefault(value, len(self.codes)))

    def to_numpy(self, where: str) -> np.ndarray:
        if self.kind == "number":
            data = np.frombuffer(self.values, dtype=float).copy() if len(self.values) else np.zeros(0)
            return data.reshape(-1, self.width) if self.width else data
        codes = np.array(self.values, dtype=np.int64)
        if self.kind == "boolean":
            if np.any(codes < 0):
                raise ValueError(f"{where} has gaps")
            return codes.astype(bool)
        names = np.array([None, *self.codes], dtype=object)
        return names[codes + 1]


def _field_kind(topic: str, name: str) -> tuple[str, int]:
    spec = next((c for c in CHANNELS if c.topic == topic), None)
    prop = spec.json_schema()["properties"].get(name) if spec is not None else None
    if prop is None:
        raise ValueError(f"{name!r} is not a field of {topic} in the channel registry")
    kind = prop["type"]
    if kind == "array" and "minItems" in prop and prop["minItems"] == prop["maxItems"]:
        return "number", int(prop["minItems"])
    if kind not in ("number", "boolean", "string"):
        raise ValueError(f"{topic} field {name!r} ({kind}) cannot be read as a column")
    return kind, 0


class ColumnSink:
    """Receives checked messages and keeps only the chosen fields (as arrays) and whole topics."""

    def __init__(self, fields: Mapping[str, Sequence[str]], whole: Sequence[str]) -> None:
        self.times = {topic: array("d") for topic in fields}
        self.columns = {topic: {name: _Column(*_field_kind(topic, name)) for name in names}
                        for topic, names in fields.items()}
        self.whole: dict[str, list[dict[str, Any]]] = {topic: [] for topic in whole}
        self.counts: dict[str, int] = {}
        self.last_t: dict[str, float] = {}

    def add_alias(self, topic: str, like: str) -> None:
        """Keep ``topic`` as ``like`` is kept (the same fields, or whole): a fleet drone's ``/cf1/state``
        as ``/state``."""
        if like in self.columns:
            self.times[topic] = array("d")
            self.columns[topic] = {name: _Column(col.kind, col.width) for name, col in self.columns[like].items()}
        if like in self.whole:
            self.whole[topic] = []

    def __call__(self, topic: str, msg: dict[str, Any]) -> None:
        t = msg["t"]
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.last_t[topic] = t
        columns = self.columns.get(topic)
        if columns is not None:
            self.times[topic].append(t)
            for name, column in columns.items():
                column.add(msg.get(name))
        if topic in self.whole:
            self.whole[topic].append(msg)


@dataclass(frozen=True)
class LogColumns:
    """Chosen fields of a log as arrays (built while streaming), and a few small topics whole.

    Offers the ``times``/``array``/``topic``/``count`` interface of ``LogData`` for those.
    """

    path: Path
    config: dict[str, Any] | None
    software_version: str | None
    truncated: bool
    note: str
    damage: LogDamage
    sink: ColumnSink

    def count(self, topic: str) -> int:
        return self.sink.counts.get(topic, 0)

    def times(self, topic: str) -> np.ndarray:
        t = self.sink.times[topic]  # KeyError: the topic was not asked for
        return np.frombuffer(t, dtype=float).copy() if len(t) else np.zeros(0)

    def array(self, topic: str, field_name: str) -> np.ndarray:
        column = self.sink.columns[topic][field_name]
        return column.to_numpy(f"{self.path.name}: field {field_name!r} on {topic}")

    def present(self, topic: str, field_name: str) -> int:
        return self.sink.columns[topic][field_name].present

    def topic(self, name: str) -> list[dict[str, Any]]:
        """Messages of a topic read whole ([] if it has none); only the topics asked for."""
        if name not in self.sink.whole:
            raise KeyError(f"topic {name} was not read whole")
        return self.sink.whole[name]

    def end_time(self) -> float:
        ends = [t for name, t in self.sink.last_t.items() if name != "/summary"]
        return max(ends) if ends else 0.0
