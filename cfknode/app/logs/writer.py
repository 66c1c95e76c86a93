"""One self-describing MCAP file per flight: the writer (the reader is ``logreader``).

Messages are JSON, on channels that carry a JSON Schema, so Foxglove opens a log as is.
Every message's MCAP log time is the flight time in nanoseconds, and its payload repeats it as
``t`` in seconds. The channels are the registry ``logformat.CHANNELS`` (see docs/logs.md).

Crash safety: the file is flushed to the operating system (its chunk ends) whenever a message
comes ``flush_interval`` seconds of flight time after the last flush, so the chunks of a flight
are the same however loaded the machine. A background thread flushes a writer that has had no
message for that long in wall time, so a process that hangs, then dies, loses at most about one
interval.
The config and software version sit at the start of the file (MCAP metadata and the ``/config``
channel), flushed at once, so even a file cut short right after take-off still names its setup.
``read_log`` reads such a truncated file up to its last complete record.
"""

from __future__ import annotations

import contextlib
import json
import json.encoder
import logging
import math
import re
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from mcap.writer import CompressionType, Writer

# The registry and the reader are re-exported: callers import them from here too.
from cfknode.app.logs.format import (
    CHANNELS,
    MCAP_MAGIC,
    METADATA_NAME,
    ChannelSpec,
    LogError,
    channels_markdown,
    check_message,
)
from cfknode.app.logs.reader import LogData, read_log

__all__ = [
    "CHANNELS",
    "ChannelSpec",
    "Chunks",
    "FlightLog",
    "LogData",
    "LogError",
    "MCAP_MAGIC",
    "METADATA_NAME",
    "channels_markdown",
    "check_message",
    "read_log",
]

_logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Chunks:
    """How the log's MCAP chunks are cut and compressed: "lz4", "zstd" or "none" (see ``FlightLog.create``)."""

    size: int = 128 * 1024  # bytes
    compression: str = "lz4"
_MAX_T = 1.8e10  # s: the largest flight time whose nanoseconds fit MCAP's u64 log time


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


class _CountedStream:
    """The log file as the MCAP writer sees it: counting the writes that succeeded tells the log
    when a closed chunk reached the file, so a later failure knows what it lost."""

    def __init__(self, stream: BinaryIO) -> None:
        self._stream = stream
        self.writes = 0

    def write(self, data: bytes) -> int:
        n = self._stream.write(data)
        self.writes += 1
        return n

    def tell(self) -> int:
        return self._stream.tell()

    def flush(self) -> None:
        self._stream.flush()

    def close(self) -> None:
        self._stream.close()


class FlightLog:
    """Writes one flight's MCAP log. Create with ``FlightLog.create``; use as a context manager.

    ``write`` is thread-safe (a lock guards the MCAP writer, which the flush thread also uses).
    """

    def __init__(
        self,
        path: Path,
        stream: _CountedStream,
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
        self._last_flush = self._last_write = time.monotonic()  # wall times: only the backstop reads them
        # Chunks end by flight time (and size, and flush channels), so a log's chunks are the same
        # on a quiet machine and a loaded one.
        self._flush_t = 0.0  # latest flight time written when a chunk last ended
        self._t_max = 0.0
        self._dirty = False
        self._closed = False
        self._count = 0
        self._dropped = 0
        self._failure: str | None = None
        # Earliest flight time written since a chunk last reached the file: what a failure loses.
        self._unflushed_from: float | None = None
        self._lost_from: float | None = None
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
        chunks: Chunks = Chunks(),
        channels: tuple[ChannelSpec, ...] = CHANNELS,
    ) -> FlightLog:
        """Open a new log ``<directory>/YYYYmmdd-HHMMSS-<hint>.mcap`` (a ``-k`` suffix if taken).

        ``started`` (default: now, local time) names the file and is stored in the metadata.
        ``flush_interval`` is the most flight time that written data waits before reaching the OS
        (a chunk ends then); a writer that stops writing for that long in wall time is flushed too.
        ``chunks.compression``: "lz4", "zstd" or "none", per chunk. lz4 and 128 KiB chunks keep the
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
            if chunks.compression not in kinds:
                raise ValueError(f"compression must be one of {sorted(kinds)}, got {chunks.compression!r}")
            counted = _CountedStream(stream)
            writer = Writer(counted, chunk_size=chunks.size, compression=kinds[chunks.compression])
            writer.start(profile="", library=f"cfknode {software_version}")
            config_json = json.dumps(_finite_or_none(dict(config)), default=_to_json, sort_keys=True)
            writer.add_metadata(METADATA_NAME, {
                "software_version": software_version,
                "started": started.isoformat(timespec="seconds"),
                "name": hint,
                "config": config_json,
            })
            topics: dict[str, tuple[int, bool]] = {}
            for spec in channels:  # a fleet's log adds each drone's channels (/cf1/state, ...)
                schema_id = writer.register_schema(
                    spec.schema_name, "jsonschema", json.dumps(spec.json_schema()).encode()
                )
                channel_id = writer.register_channel(spec.topic, "json", schema_id, {"description": spec.description})
                topics[spec.topic] = (channel_id, spec.flush)
        except BaseException as exc:
            with contextlib.suppress(OSError):  # a full disk refuses the buffered bytes again
                stream.close()
            path.unlink(missing_ok=True)  # no empty, unreadable file left behind
            if isinstance(exc, OSError):
                reason = exc.strerror or exc
                raise LogError(f"take-off refused: cannot write the flight log ({path}: {reason})") from None
            raise
        log = cls(path, counted, writer, topics, flush_interval)
        # /config is a flush channel: with it the file's first chunk (schemas, channels) is on disk now.
        log.write("/config", 0.0, {"software_version": software_version, "config": json.loads(config_json)})
        if log.failure is not None:  # not even its start reached the disk (full): no flight without a log
            log.close()
            path.unlink(missing_ok=True)
            raise LogError(f"take-off refused: cannot write the flight log ({log.failure})")
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
    def lost_from(self) -> float | None:
        """After a write failure: the flight time (s) from which messages did not reach the file.

        The failed write takes the open chunk's messages with it, so this is the earliest time
        written since a chunk last reached the file. None if the log never failed, or lost no message.
        """
        return self._lost_from

    @property
    def messages_dropped(self) -> int:
        """Messages discarded after a write failure."""
        return self._dropped

    def incomplete(self) -> str | None:
        """A phrase for the flight's summary when the log stopped writing, else None.

        Says from which flight time messages are missing and why, e.g. "incomplete from
        t = 12.34 s (/path: No space left on device; 4100 messages not written)".
        """
        if self._failure is None:
            return None
        where = (f"from t = {self._lost_from:.2f} s" if self._lost_from is not None
                 else "at its end (index and footer)")
        return f"incomplete {where} ({self._failure}; {self._dropped} messages not written)"

    def write(self, topic: str, t: float, msg: Mapping[str, Any]) -> None:
        """Log ``msg`` on ``topic`` at flight time ``t`` (s). numpy values become plain JSON.

        ``msg`` must not contain ``t``: the payload's ``t`` is the flight time given here.
        An OS error while writing (full disk) never reaches the caller, who is flying: it is
        logged once, kept in ``failure``, and later messages are counted in ``messages_dropped``.
        """
        entry, t = self._entry(topic, t)
        if "t" in msg:
            raise ValueError(f"message on {topic} must not contain 't' (it is the write time)")
        payload = {"t": t}
        payload.update(msg)
        text = self._encode(payload)
        if "NaN" in text or "Infinity" in text:  # rare: a failed solve; re-encode with nulls
            text = self._encode(_finite_or_none(payload))
        self._add(topic, entry, t, text.encode())

    def add_encoded_channel(self, topic: str, schema_name: str, schema_encoding: str, schema: bytes,
                            message_encoding: str) -> None:
        """A channel whose messages the caller encodes (Foxglove's protobuf schemas, see docs/foxglove.md).

        ``read_log`` passes such channels over; Foxglove decodes them with ``schema``."""
        if topic in self._topics:
            raise ValueError(f"flight-log topic {topic!r} exists already")
        with self._lock:
            if self._closed:
                raise ValueError(f"flight log {self._path.name} is closed")
            schema_id = self._writer.register_schema(schema_name, schema_encoding, schema)
            self._topics[topic] = (self._writer.register_channel(topic, message_encoding, schema_id), False)

    def write_encoded(self, topic: str, t: float, data: bytes) -> None:
        """Log an encoded message on a channel from ``add_encoded_channel``; failures as ``write``."""
        entry, t = self._entry(topic, t)
        self._add(topic, entry, t, data)

    def _entry(self, topic: str, t: float) -> tuple[tuple[int, bool], float]:
        """The topic's (channel id, flush at once) and the time as a float; a wiring bug raises ValueError."""
        entry = self._topics.get(topic)
        if entry is None:
            raise ValueError(f"unknown flight-log topic {topic!r}; known: {', '.join(self._topics)}")
        t = float(t)
        if not 0.0 <= t < _MAX_T:
            raise ValueError(f"flight-log time must be finite and >= 0, got {t} on {topic}")
        return entry, t

    def _add(self, topic: str, entry: tuple[int, bool], t: float, data: bytes) -> None:
        ns = round(t * 1e9)
        channel_id, flush_now = entry
        with self._lock:
            if self._closed:
                raise ValueError(f"flight log {self._path.name} is closed")
            if self._failure is not None:
                self._dropped += 1
                return
            if self._unflushed_from is None or t < self._unflushed_from:
                self._unflushed_from = t
            writes = self._stream.writes
            try:
                self._writer.add_message(channel_id, ns, data, ns)
            except OSError as exc:  # the add closed a full chunk, and that write failed
                self._dropped += 1
                self._fail(exc)
                return
            if self._stream.writes != writes:  # it closed a chunk (this message its last), now in the file
                self._unflushed_from = None
            self._count += 1
            self._dirty = True
            self._t_max = max(self._t_max, t)
            self._last_write = time.monotonic()
            if flush_now or t - self._flush_t >= self._flush_interval:
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
        self._lost_from = self._unflushed_from
        _logger.error("flight log stopped writing: %s", self._failure)

    def _flush_locked(self) -> None:
        self._writer.flush()
        self._flush_t = self._t_max
        self._unflushed_from = None
        self._dirty = False
        self._last_flush = time.monotonic()

    def _flush_loop(self) -> None:
        # Backstop for a loop that stops writing (hung, or between flights): the write path
        # flushes on its own while messages flow.
        while not self._stop.wait(self._flush_interval / 2):
            with self._lock:
                if self._closed:
                    return
                now = time.monotonic()
                # Only a writer that has stopped writing: a flowing one ends its chunks by flight time.
                stale = min(now - self._last_flush, now - self._last_write) >= self._flush_interval
                if self._failure is None and self._dirty and stale:
                    try:
                        self._flush_locked()
                    except OSError as exc:
                        self._fail(exc)


