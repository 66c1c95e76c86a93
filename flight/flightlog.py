"""One self-describing MCAP file per flight (DESIGN.md section 7).

Messages are JSON, on channels that carry a JSON Schema, so Foxglove opens a log as is.
Every message's MCAP log time is the flight time in nanoseconds, and its payload repeats it as
``t`` in seconds.

Crash safety: the file is flushed to the operating system whenever ``flush_interval`` seconds
of wall time have passed since the last flush. A background thread does the same while no
messages arrive, so a process that dies (or hangs, then dies) loses at most about one interval.
The config and software version sit at the start of the file (MCAP metadata and the ``/config``
channel), flushed at once, so even a file cut short right after take-off still names its setup.
``read_log`` reads such a truncated file up to its last complete record.

Channels are a fixed registry, ``CHANNELS``. Adding one is one ``ChannelSpec(...)`` line there.
``channels_markdown()`` renders the registry as a table for the README.
"""

from __future__ import annotations

import io
import json
import json.encoder
import logging
import math
import re
import struct
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import breakup_chunk
from mcap.writer import CompressionType, Writer

__all__ = [
    "CHANNELS",
    "ChannelSpec",
    "FlightLog",
    "LogData",
    "LogError",
    "channels_markdown",
    "check_message",
    "read_log",
]

_logger = logging.getLogger(__name__)
MCAP_MAGIC = b"\x89MCAP0\r\n"
METADATA_NAME = "cfknode"
_MAX_T = 1.8e10  # s: the largest flight time whose nanoseconds fit MCAP's u64 log time
# What a complete record with bad contents raises while decoding (CRC, decompression, JSON).
_CORRUPT = (McapError, ValueError, KeyError, RuntimeError, struct.error, zstandard.ZstdError)


class LogError(Exception):
    """A flight log cannot be written or read; the message is one line naming the file."""


# --- Channel registry --------------------------------------------------------------------------


def _num(description: str) -> dict[str, Any]:
    return {"type": "number", "description": description}


def _vec(n: int, description: str) -> dict[str, Any]:
    return {
        "type": "array",
        "items": {"type": "number"},
        "minItems": n,
        "maxItems": n,
        "description": description,
    }


def _bool(description: str) -> dict[str, Any]:
    return {"type": "boolean", "description": description}


def _str(description: str) -> dict[str, Any]:
    return {"type": "string", "description": description}


def _obj(description: str) -> dict[str, Any]:
    return {"type": "object", "description": description}


_T = _num("flight time, s (the MCAP log time is the same, in ns)")


@dataclass(frozen=True)
class ChannelSpec:
    """One topic of the flight log: its JSON Schema fields and its flush policy.

    ``flush=True`` writes the topic to disk at once (rare, precious messages: config, events,
    summary); other topics follow the periodic flush.
    """

    topic: str
    schema_name: str
    description: str
    required: Mapping[str, Mapping[str, Any]]
    optional: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    flush: bool = False

    def json_schema(self) -> dict[str, Any]:
        return {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": self.schema_name,
            "description": self.description + " Non-finite numbers are written as null.",
            "type": "object",
            "properties": {"t": _T, **self.required, **self.optional},
            "required": ["t", *self.required],
            "additionalProperties": True,
        }


CHANNELS: tuple[ChannelSpec, ...] = (
    ChannelSpec(
        "/config", "cfknode.Config", "The flight's configuration and software version.",
        {"software_version": _str("cfknode version"), "config": _obj("cfknode Config.to_dict()")},
        flush=True,
    ),
    ChannelSpec(
        "/state", "cfknode.State", "State estimate used by the controller, one per tick.",
        {"p": _vec(3, "position, world, m"), "v": _vec(3, "velocity, world, m/s"),
         "q": _vec(4, "attitude quaternion body->world, w x y z")},
        {"p_true": _vec(3, "simulator: true position, m"), "v_true": _vec(3, "simulator: true velocity, m/s"),
         "q_true": _vec(4, "simulator: true attitude, w x y z")},
    ),
    ChannelSpec(
        "/reference", "cfknode.Reference", "Reference at the tick time.",
        {"p": _vec(3, "position, m"), "v": _vec(3, "velocity, m/s"), "a": _vec(3, "acceleration, m/s^2"),
         "yaw": _num("yaw, rad")},
    ),
    ChannelSpec(
        "/command", "cfknode.Command", "Command sent this tick: world acceleration and the RPYT setpoint.",
        {"acc": _vec(3, "commanded acceleration, world, m/s^2"), "roll_deg": _num("roll, deg"),
         "pitch_deg": _num("pitch, deg (cflib sign convention)"), "yawrate_deg": _num("yaw rate, deg/s"),
         "thrust": _num("thrust command, 0..65535"),
         "source": _str("which controller produced it: mpc, fallback, hold, stop, ...")},
    ),
    ChannelSpec(
        "/tick", "cfknode.Tick", "Timing of one control tick.",
        {"compute_s": _num("tick compute time, wall s"), "solve_s": _num("MPC solve time, wall s"),
         "missed": _bool("the tick missed its deadline"), "mpc_ok": _bool("the MPC solution was used")},
        {"status": _str("solver status")},
    ),
    ChannelSpec(
        "/mocap", "cfknode.Mocap", "Motion-capture frame handed to the estimator.",
        {"received": _bool("a frame arrived (false: dropout, p and q absent)")},
        {"p": _vec(3, "position, m"), "q": _vec(4, "attitude, w x y z"),
         "stamp": _num("frame sample time, s, when it differs from t")},
    ),
    ChannelSpec(
        "/events", "cfknode.Event", "Discrete events: supervisor transitions, warnings, faults.",
        {"level": _str("debug, info, warning, error or critical"), "text": _str("what happened")},
        {"source": _str("the part that raised it"),
         "part": _str("internal errors: the part of the flight that raised"),
         "traceback": _str("internal errors: the traceback, logged once per distinct error")},
        flush=True,
    ),
    ChannelSpec(
        "/safety", "cfknode.Safety", "Safety supervisor status: at every transition and at 10 Hz.",
        {"state": _str("IDLE, PREFLIGHT, TAKEOFF, TRACK, LAND, LANDED or EMERGENCY")},
        {"reason": _str("why the supervisor is landing or stopped (empty when nominal)"),
         "pose_age_s": _num("age of the newest mocap frame, s"),
         "fence_margin_m": _num("distance inside the hard geofence, m (< 0: outside)"),
         "tracking_error_m": _num("position minus reference, m"), "battery_v": _num("filtered battery voltage, V"),
         "link_silence_s": _num("time since the radio link last answered, s"),
         "fallback_ticks": _num("MPC failures in a row (the geometric controller flew them)")},
    ),
    ChannelSpec(
        "/model", "cfknode.Model",
        "KNODE model events: a network swapped in, rejected by the gate, rolled back, dropped for nominal by the monitor; trainer crash or restart.",
        {"version": _num("model version the event is about (0 = nominal)"),
         "event": _str("swap, reject, rollback, drop, crash or restart")},
        {"reason": _str("why it was rejected or rolled back, or what failed"), "loss": _num("training loss"),
         "val_error": _num("validation error (online: candidate's one-step velocity RMSE on fresh data, m/s)"),
         "swap_ms": _num("time to write the solver parameters, ms"),
         "queue": {"type": "array", "items": _num("version"), "description": "versions flying after it, oldest first"},
         "round": _num("online training round"), "window": _vec(2, "training window [t0, t1], flight time s"),
         "val_error_current": _num("the flying model's one-step velocity RMSE on the same data, m/s"),
         "val_error_nominal": _num("the nominal model's one-step velocity RMSE on the same data, m/s"),
         "max_residual": _num("largest residual component on the recent data, m/s^2"),
         "val_pairs": _num("held-out pairs the gate judged on"),
         "control_gain": _vec(2, "extreme eigenvalues of sym(I + dr/du) on the envelope"),
         "velocity_gain": _num("largest eigenvalue of sym(dr/dv) on the envelope, 1/s"),
         "cross_gain": _num("largest |off-diagonal| of dr/du on the envelope"),
         "train_wall_s": _num("trainer wall time of the round, s"),
         "latency_s": _num("wall time from sending the window to the result, s"),
         "install_ms": _num("gate + folding + swap, spread over tick gaps, ms"),
         "slice_ms": _num("the longest of those slices (what one tick gap absorbed), ms")},
        flush=True,
    ),
    ChannelSpec(
        "/training", "cfknode.Training", "One online training round's result (cfknode.models.trainer_process).",
        {"round": _num("training round, 1.."), "version": _num("candidate model version"),
         "window": _vec(2, "training window [t0, t1], flight time s"), "ok": _bool("the round produced a model")},
        {"base_version": _num("version the window was flown with"), "pairs": _num("training pairs"),
         "loss": _num("final data loss, (m/s^2)^2"), "val_rmse_model": _num("trainer's held-out RMSE, m/s"),
         "val_rmse_nominal": _num("nominal model's held-out RMSE, m/s"),
         "max_abs_residual": _num("largest residual on the training inputs, m/s^2"),
         "train_wall_s": _num("trainer wall time of the round, s"), "train_cpu_s": _num("trainer CPU time, s"),
         "latency_s": _num("wall time from sending the window to the result, s"),
         "t_col": _num("window length, s"), "error": _str("why the round failed (empty when ok)")},
    ),
    ChannelSpec(
        "/summary", "cfknode.Summary", "The flight summary (cfknode.flight.summary.FlightSummary.to_dict()).",
        {}, flush=True,
    ),
)


def channels_markdown(channels: tuple[ChannelSpec, ...] = CHANNELS) -> str:
    """The registry as a Markdown table (topic, schema, fields), for the README."""
    rows = ["| topic | schema | fields (optional in brackets) |", "|---|---|---|"]
    for spec in channels:
        fields = ["t", *spec.required, *(f"[{name}]" for name in spec.optional)]
        rows.append(f"| `{spec.topic}` | `{spec.schema_name}` | {', '.join(fields)} |")
    return "\n".join(rows)


def check_message(topic: str, msg: Mapping[str, Any], channels: tuple[ChannelSpec, ...] = CHANNELS) -> list[str]:
    """Problems of a message (as read back, with ``t``) against its channel's schema; [] if none.

    Checks presence of required fields, the JSON type of each known field and array lengths.
    For tests and offline checks, not the hot path.
    """
    spec = next((c for c in channels if c.topic == topic), None)
    if spec is None:
        return [f"unknown topic {topic!r}"]
    schema = spec.json_schema()
    problems = [f"{topic}: missing {name!r}" for name in schema["required"] if name not in msg]
    for name, prop in schema["properties"].items():
        if name in msg and not _matches(msg[name], prop):
            problems.append(f"{topic}: field {name!r} = {msg[name]!r} is not {prop['type']}"
                            + (f"[{prop['minItems']}]" if "minItems" in prop else ""))
    return problems


def _matches(value: Any, prop: Mapping[str, Any]) -> bool:
    kind = prop["type"]
    if kind == "number":  # null stands for a non-finite number
        return value is None or (isinstance(value, (int, float)) and not isinstance(value, bool))
    if kind == "boolean":
        return isinstance(value, bool)
    if kind == "string":
        return isinstance(value, str)
    if kind == "object":
        return isinstance(value, dict)
    if kind == "array":
        return (isinstance(value, list) and prop.get("minItems", 0) <= len(value) <= prop.get("maxItems", len(value))
                and all(_matches(v, prop["items"]) for v in value))
    return True


# --- JSON encoding -----------------------------------------------------------------------------


def _to_json(obj: Any) -> Any:
    # Called by the encoder only for objects json cannot encode itself (numpy, mostly).
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (tuple, set, frozenset)):
        return list(obj)
    raise TypeError(f"cannot log a value of type {type(obj).__name__}")


def _finite_or_none(obj: Any) -> Any:
    """Replace non-finite floats by None: NaN is not JSON, and Foxglove's parser rejects it."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_or_none(v) for v in obj]
    if isinstance(obj, (np.ndarray, np.generic)):
        return _finite_or_none(obj.tolist() if isinstance(obj, np.ndarray) else obj.item())
    return obj


def _make_encode() -> Callable[[Any], str]:
    """A compact JSON encoder function, built once per log.

    ``JSONEncoder.encode`` rebuilds CPython's C encoder on every call (about 2 us of a 5 us
    message); building it once with ``json.encoder.c_make_encoder`` skips that. Where the C
    encoder is missing or differs, the plain encoder is used.
    """
    plain = json.JSONEncoder(default=_to_json, separators=(",", ":"), ensure_ascii=False).encode
    make = getattr(json.encoder, "c_make_encoder", None)
    if make is None:
        return plain
    try:
        iterencode = make(None, _to_json, json.encoder.encode_basestring, None, ":", ",", False, False, True)
    except TypeError:
        return plain

    def encode(obj: Any) -> str:
        return "".join(iterencode(obj, 0))

    probe = {"t": 0.25, "p": np.array([1.0, -2.5, 3.0]), "ok": True, "s": "é", "n": None, "k": 3}
    return encode if encode(probe) == plain(probe) else plain


# --- Writer ------------------------------------------------------------------------------------

_SAFE_HINT = re.compile(r"[^A-Za-z0-9._-]+")


def _open_unique(directory: Path, stamp: str, hint: str) -> tuple[Path, BinaryIO]:
    """Open a new file ``<stamp>-<hint>[-k].mcap`` exclusively: never overwrites, race-free."""
    for k in range(10_000):
        path = directory / (f"{stamp}-{hint}.mcap" if k == 0 else f"{stamp}-{hint}-{k}.mcap")
        try:
            return path, open(path, "xb")
        except FileExistsError:
            continue
    raise LogError(f"{directory}: no free log file name for {stamp}-{hint}")


class FlightLog:
    """Writes one flight's MCAP log. Create with ``FlightLog.create``; use as a context manager.

    ``write`` is thread-safe (a lock guards the MCAP writer, which the flush thread also uses).
    """

    def __init__(
        self,
        path: Path,
        stream: BinaryIO,
        writer: Writer,
        topics: Mapping[str, tuple[int, bool]],
        flush_interval: float,
    ) -> None:
        self._path = path
        self._stream = stream
        self._writer = writer
        self._topics = dict(topics)  # topic -> (channel id, flush at once)
        self._flush_interval = flush_interval
        self._encode = _make_encode()
        self._lock = threading.Lock()
        self._last_flush = time.monotonic()
        self._dirty = False
        self._closed = False
        self._count = 0
        self._dropped = 0
        self._failure: str | None = None
        self._stop = threading.Event()
        self._flusher = threading.Thread(target=self._flush_loop, name=f"flightlog:{path.name}", daemon=True)

    @classmethod
    def create(
        cls,
        directory: str | Path,
        config: Mapping[str, Any],
        software_version: str,
        name_hint: str = "flight",
        *,
        started: datetime | None = None,
        flush_interval: float = 0.5,
        chunk_size: int = 128 * 1024,
        compression: str = "lz4",
    ) -> FlightLog:
        """Open a new log ``<directory>/YYYYmmdd-HHMMSS-<hint>.mcap`` (a ``-k`` suffix if taken).

        ``started`` (default: now, local time) names the file and is stored in the metadata.
        ``flush_interval`` is the most wall time that written data waits before reaching the OS.
        ``compression``: "lz4", "zstd" or "none", per chunk. lz4 and 128 KiB chunks keep the
        occasional chunk-closing write (done inline by ``write``) near 0.5 ms; zstd files are
        about 30% smaller but close chunks 2x slower.
        """
        if flush_interval <= 0:
            raise ValueError(f"flush_interval must be > 0, got {flush_interval}")
        started = started or datetime.now()
        directory = Path(directory)
        hint = _SAFE_HINT.sub("_", name_hint).strip("._-") or "flight"
        try:
            directory.mkdir(parents=True, exist_ok=True)
            path, stream = _open_unique(directory, started.strftime("%Y%m%d-%H%M%S"), hint)
        except OSError as exc:
            raise LogError(f"{directory}: cannot create a flight log ({exc.strerror or exc})") from exc
        try:
            kinds = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
            if compression not in kinds:
                raise ValueError(f"compression must be one of {sorted(kinds)}, got {compression!r}")
            writer = Writer(stream, chunk_size=chunk_size, compression=kinds[compression])
            writer.start(profile="", library=f"cfknode {software_version}")
            config_json = json.dumps(_finite_or_none(dict(config)), default=_to_json, sort_keys=True)
            writer.add_metadata(METADATA_NAME, {
                "software_version": software_version,
                "started": started.isoformat(timespec="seconds"),
                "name": hint,
                "config": config_json,
            })
            topics: dict[str, tuple[int, bool]] = {}
            for spec in CHANNELS:
                schema_id = writer.register_schema(
                    spec.schema_name, "jsonschema", json.dumps(spec.json_schema()).encode()
                )
                channel_id = writer.register_channel(spec.topic, "json", schema_id, {"description": spec.description})
                topics[spec.topic] = (channel_id, spec.flush)
        except BaseException:
            stream.close()
            path.unlink(missing_ok=True)  # no empty, unreadable file left behind
            raise
        log = cls(path, stream, writer, topics, flush_interval)
        # /config is a flush channel: with it the file's first chunk (schemas, channels) is on disk now.
        log.write("/config", 0.0, {"software_version": software_version, "config": json.loads(config_json)})
        log._flusher.start()
        return log

    @property
    def path(self) -> Path:
        return self._path

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def messages_written(self) -> int:
        return self._count

    @property
    def failure(self) -> str | None:
        """Why the log stopped writing (an OS error such as a full disk), or None."""
        return self._failure

    @property
    def messages_dropped(self) -> int:
        """Messages discarded after a write failure."""
        return self._dropped

    def write(self, topic: str, t: float, msg: Mapping[str, Any]) -> None:
        """Log ``msg`` on ``topic`` at flight time ``t`` (s). numpy values become plain JSON.

        ``msg`` must not contain ``t``: the payload's ``t`` is the flight time given here.
        An OS error while writing (full disk) never reaches the caller, who is flying: it is
        logged once, kept in ``failure``, and later messages are counted in ``messages_dropped``.
        """
        entry = self._topics.get(topic)
        if entry is None:
            raise ValueError(f"unknown flight-log topic {topic!r}; known: {', '.join(self._topics)}")
        t = float(t)
        if not 0.0 <= t < _MAX_T:
            raise ValueError(f"flight-log time must be finite and >= 0, got {t} on {topic}")
        if "t" in msg:
            raise ValueError(f"message on {topic} must not contain 't' (it is the write time)")
        payload = {"t": t}
        payload.update(msg)
        text = self._encode(payload)
        if "NaN" in text or "Infinity" in text:  # rare: a failed solve; re-encode with nulls
            text = self._encode(_finite_or_none(payload))
        ns = round(t * 1e9)
        channel_id, flush_now = entry
        with self._lock:
            if self._closed:
                raise ValueError(f"flight log {self._path.name} is closed")
            if self._failure is not None:
                self._dropped += 1
                return
            try:
                self._writer.add_message(channel_id, ns, text.encode(), ns)
            except OSError as exc:  # the add closed a full chunk, and that write failed
                self._dropped += 1
                self._fail(exc)
                return
            self._count += 1
            self._dirty = True
            if flush_now or time.monotonic() - self._last_flush >= self._flush_interval:
                try:
                    self._flush_locked()
                except OSError as exc:
                    self._fail(exc)

    def flush(self) -> None:
        """Write everything so far to the OS now (ends the current chunk)."""
        with self._lock:
            if not self._closed and self._dirty and self._failure is None:
                try:
                    self._flush_locked()
                except OSError as exc:
                    self._fail(exc)

    def close(self) -> None:
        """Write the MCAP summary section and footer, and close the file. Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            try:
                if self._failure is None:
                    self._writer.finish()
            except OSError as exc:
                self._fail(exc)
            finally:
                try:
                    self._stream.close()
                except OSError as exc:  # buffered bytes that a failed disk still refuses
                    if self._failure is None:
                        self._fail(exc)
        self._stop.set()
        if self._flusher.is_alive() and self._flusher is not threading.current_thread():
            self._flusher.join()

    def __enter__(self) -> FlightLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _fail(self, exc: OSError) -> None:
        self._failure = f"{self._path}: {exc.strerror or exc}"
        _logger.error("flight log stopped writing: %s", self._failure)

    def _flush_locked(self) -> None:
        self._writer.flush()
        self._dirty = False
        self._last_flush = time.monotonic()

    def _flush_loop(self) -> None:
        # Backstop for a loop that stops writing (hung, or between flights): the write path
        # flushes on its own while messages flow.
        while not self._stop.wait(self._flush_interval / 2):
            with self._lock:
                if self._closed:
                    return
                stale = time.monotonic() - self._last_flush >= self._flush_interval
                if self._failure is None and self._dirty and stale:
                    try:
                        self._flush_locked()
                    except OSError as exc:
                        self._fail(exc)


# --- Reader ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LogData:
    """A flight log read back: messages per topic (dicts, as written plus ``t``), config, version.

    ``truncated`` is True when the file has no MCAP footer (the writer never closed it);
    ``note`` says where and why reading stopped early, or is "".
    """

    path: Path
    messages: Mapping[str, list[dict[str, Any]]]
    config: dict[str, Any] | None
    software_version: str | None
    metadata: Mapping[str, Mapping[str, str]]
    schemas: Mapping[str, Mapping[str, Any]]
    truncated: bool
    note: str = ""

    @property
    def topics(self) -> list[str]:
        return list(self.messages)

    def topic(self, name: str) -> list[dict[str, Any]]:
        """Messages of ``name`` in file order ([] if the topic has none)."""
        return self.messages.get(name, [])

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
        return np.array([gap if v is None else v for v in values], dtype=float).reshape(len(values), width)


def read_log(path: str | Path) -> LogData:
    """Read a flight log; a truncated file is read up to its last complete record.

    Raises ``LogError`` (one line, naming the file) when the file is missing or not MCAP.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as exc:
        raise LogError(f"{path}: cannot read flight log ({exc.strerror or exc})") from exc
    if len(data) == 0:
        raise LogError(f"{path}: empty file, not an MCAP flight log")
    if not data.startswith(MCAP_MAGIC):
        raise LogError(f"{path}: not an MCAP flight log (bad magic bytes)")

    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    messages: dict[str, list[dict[str, Any]]] = {}
    metadata: dict[str, dict[str, str]] = {}
    note = ""
    complete = False
    view = memoryview(data)
    pos = len(MCAP_MAGIC)

    def take(record: Any) -> None:
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
            messages.setdefault(record.topic, [])
        elif isinstance(record, Message):
            channel = channels.get(record.channel_id)
            if channel is not None and channel.message_encoding == "json":
                messages[channel.topic].append(json.loads(record.data))

    while True:
        if pos + 9 > len(data):
            note = note or f"truncated after byte {pos} (no footer)"
            break
        opcode, length = struct.unpack_from("<BQ", data, pos)
        body_start = pos + 9
        if length > len(data) - body_start:
            note = f"truncated inside a record at byte {pos} (opcode {opcode:#04x})"
            break
        stream = ReadDataStream(io.BytesIO(view[body_start:body_start + length]))
        try:
            if opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                take((Schema if opcode == Opcode.SCHEMA else Channel).read(stream))
            elif opcode == Opcode.MESSAGE:
                take(Message.read(stream, length))
            elif opcode == Opcode.CHUNK:
                for record in breakup_chunk(Chunk.read(stream), validate_crc=True):
                    take(record)
            elif opcode == Opcode.METADATA:
                record = Metadata.read(stream)
                metadata[record.name] = dict(record.metadata)
            elif opcode == Opcode.FOOTER:
                Footer.read(stream)
                complete = data[body_start + length:body_start + length + len(MCAP_MAGIC)] == MCAP_MAGIC
                if not complete:
                    note = "footer without closing magic"
                break
        except _CORRUPT as exc:
            # A complete but unreadable record: corruption, not a crash cut. Keep what came before.
            note = f"unreadable record at byte {pos} (opcode {opcode:#04x}): {type(exc).__name__}: {exc}"
            break
        pos = body_start + length

    return LogData(
        path=path,
        messages=messages,
        config=_config_of(metadata, messages),
        software_version=_version_of(metadata, messages),
        metadata=metadata,
        schemas={
            c.topic: json.loads(schemas[c.schema_id].data)
            for c in channels.values()
            if c.schema_id in schemas and schemas[c.schema_id].encoding == "jsonschema"
        },
        truncated=not complete,
        note=note,
    )


def _config_of(metadata: Mapping[str, Mapping[str, str]], messages: Mapping[str, list[dict]]) -> dict | None:
    if METADATA_NAME in metadata and "config" in metadata[METADATA_NAME]:
        return json.loads(metadata[METADATA_NAME]["config"])
    first = messages.get("/config")
    return first[0].get("config") if first else None


def _version_of(metadata: Mapping[str, Mapping[str, str]], messages: Mapping[str, list[dict]]) -> str | None:
    if METADATA_NAME in metadata and "software_version" in metadata[METADATA_NAME]:
        return metadata[METADATA_NAME]["software_version"]
    first = messages.get("/config")
    return first[0].get("software_version") if first else None
