"""Reading flight logs: streamed record by record, every message checked, damage counted.

``read_log`` keeps every message (dicts); ``read_columns`` keeps only chosen fields as numpy
arrays, so a long flight reads in little memory. Both stream the file: at most one record (a
chunk, 128 KiB as cfknode writes them) is in memory at a time besides what is kept.

What is refused, with one ``LogError`` line naming the file: a missing file, anything that is
not a regular file (a FIFO would block, a device never ends), a file without the MCAP magic.
What is skipped and counted in ``LogDamage`` (the rest is used): a chunk that fails its CRC or
does not decompress (its flight-time span is reported missing), an incomplete record where
the file was cut, messages that are not JSON objects or lack their channel's fields (see
``logformat.message_checker``), a schema or configuration metadata that is not JSON.
"""

from __future__ import annotations

import io
import json
import os
import struct
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Metadata, Schema

from cfknode.app.logs.data import ColumnSink, LogColumns, LogDamage, LogData, require_messages
from cfknode.kernel.bounded_input import open_regular
from cfknode.app.logs.format import MCAP_MAGIC, METADATA_NAME, LogError, message_checker

__all__ = ["LogColumns", "LogDamage", "LogData", "LogError", "MAX_RECORD_BYTES", "read_columns", "read_log",
           "require_messages"]

# Far above any chunk a writer makes (cfknode: 128 KiB; other tools: a few MiB). A record
# claiming more is a broken length field, and reading it would take unbounded memory.
MAX_RECORD_BYTES = 256 << 20
# Logs are streamed a record at a time, so the cap is far above any flight's (hours at 400 Hz).
MAX_LOG_BYTES = 64 << 30
_HEADER = struct.Struct("<BQ")  # opcode, record length
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK = struct.Struct("<QQQI")  # start time, end time, uncompressed size, uncompressed CRC
# What decoding a complete record with bad contents raises (lengths, UTF-8, decompression).
_BAD_RECORD = (ValueError, struct.error, EOFError, RuntimeError, zstandard.ZstdError, McapError, IndexError,
               OverflowError, MemoryError)


class _BadRecord(Exception):
    """A complete record whose contents cannot be decoded."""


def read_log(path: str | Path) -> LogData:
    """Read a flight log, every message; a damaged or truncated file is read around the damage.

    Raises ``LogError`` (one line, naming the file) when the file is missing, not a regular
    file, or not MCAP. ``LogData.damage`` says what was skipped.
    """
    path = Path(path)
    messages: dict[str, list[dict[str, Any]]] = {}

    def keep(topic: str, msg: dict[str, Any]) -> None:
        messages[topic].append(msg)

    scan = _Scan(path, keep, on_channel=lambda topic: messages.setdefault(topic, []))
    scan.run()
    return LogData(path=path, messages=messages, config=scan.config, software_version=scan.software_version,
                   metadata=scan.metadata, schemas=scan.schemas, truncated=scan.damage.truncated,
                   note=scan.damage.line(), damage=scan.damage)


def read_columns(path: str | Path, fields: Mapping[str, Sequence[str]], whole: Sequence[str] = (),
                 sink: ColumnSink | None = None) -> LogColumns:
    """Read only ``fields`` (topic -> registry field names) as arrays, and the ``whole`` topics as dicts.

    The memory kept is about 8 bytes per number asked for; see ``read_log`` for errors. ``sink``:
    one made for these fields that keeps more (a fleet log's drones: logs/fleet_log.py).
    """
    path = Path(path)
    sink = sink if sink is not None else ColumnSink(fields, whole)
    scan = _Scan(path, sink)
    scan.run()
    return LogColumns(path=path, config=scan.config, software_version=scan.software_version,
                      truncated=scan.damage.truncated, note=scan.damage.line(), damage=scan.damage, sink=sink)


def open_log_file(path: Path) -> tuple[BinaryIO, int]:
    """Open a regular file for reading and return it with its size; ``LogError`` for anything else."""
    return open_regular(path, MAX_LOG_BYTES, LogError, "flight log", buffering=1 << 20)


@dataclass
class _Scan:
    """One pass over a log file: records in file order, messages handed to ``on_message``."""

    path: Path
    on_message: Callable[[str, dict[str, Any]], None]
    on_channel: Callable[[str], Any] = lambda topic: None
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    schemas: dict[str, dict[str, Any]] = field(default_factory=dict)
    config: dict[str, Any] | None = None
    software_version: str | None = None
    damage: LogDamage = field(default_factory=LogDamage)
    # Working state of the pass.
    _schema_data: dict[int, tuple[str, str, bytes]] = field(default_factory=dict)  # id -> name, encoding, data
    _channels: dict[int, tuple[str, Callable[[Any], str | None]] | None] = field(default_factory=dict)
    _bad: dict[str, int] = field(default_factory=dict)  # "topic: problem" -> messages
    _gaps: list[tuple[float, float]] = field(default_factory=list)
    _warnings: list[str] = field(default_factory=list)
    _first_config: dict[str, Any] | None = None
    _end_t: float | None = None

    def run(self) -> None:
        f, size = open_log_file(self.path)
        with f:
            self._read(f, size)

    def _read(self, f: BinaryIO, size: int) -> None:
        if size == 0:
            raise LogError(f"{self.path}: empty file, not an MCAP flight log")
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise LogError(f"{self.path}: not an MCAP flight log (bad magic bytes)")
        skipped_records = skipped_bytes = tail = 0
        stopped = ""
        complete = False
        pos = len(MCAP_MAGIC)
        while True:
            header = f.read(_HEADER.size)
            if len(header) < _HEADER.size:
                tail = len(header)
                stopped = f"incomplete record at byte {pos}, {tail} bytes skipped" if header else ""
                break
            opcode, length = _HEADER.unpack(header)
            body_start = pos + _HEADER.size
            if length > size - body_start:
                tail = size - pos
                stopped = f"incomplete record at byte {pos}, {tail} bytes skipped"
                break
            if length > MAX_RECORD_BYTES:
                tail = size - pos
                stopped = f"record at byte {pos} claims {length} bytes, unreadable from there: {tail} bytes skipped"
                break
            if opcode == Opcode.FOOTER:
                f.seek(length, io.SEEK_CUR)
                complete = f.read(len(MCAP_MAGIC)) == MCAP_MAGIC
                stopped = "" if complete else f"footer at byte {pos} without the closing magic"
                break
            if opcode in (Opcode.CHUNK, Opcode.MESSAGE, Opcode.SCHEMA, Opcode.CHANNEL, Opcode.METADATA):
                body = f.read(length)
                if len(body) < length:  # the file shrank while being read
                    tail = _HEADER.size + len(body)
                    stopped = f"incomplete record at byte {pos}, {tail} bytes skipped"
                    break
                try:
                    self._record(opcode, memoryview(body))
                except _BadRecord as exc:
                    skipped_records += 1
                    skipped_bytes += _HEADER.size + length
                    if opcode == Opcode.CHUNK and len(body) >= _CHUNK.size:
                        start_ns, end_ns = struct.unpack_from("<QQ", body)
                        self._gaps.append((start_ns * 1e-9, end_ns * 1e-9))
                    else:
                        self._warnings.append(f"unreadable record at byte {pos} ({exc})")
            else:  # indexes, statistics, attachments: not needed to read the flight
                f.seek(length, io.SEEK_CUR)
            pos = body_start + length
        self._finish(skipped_records, skipped_bytes + tail, tail, stopped, complete)

    def _record(self, opcode: int, body: memoryview) -> None:
        try:
            if opcode == Opcode.CHUNK:
                for op, rec in _chunk_records(body):
                    self._inner(op, rec)
            elif opcode == Opcode.METADATA:
                record = Metadata.read(ReadDataStream(io.BytesIO(body)))
                self.metadata[record.name] = dict(record.metadata)
            else:
                self._inner(opcode, body)
        except _BAD_RECORD as exc:
            raise _BadRecord(f"{type(exc).__name__}: {exc}") from None

    def _inner(self, opcode: int, body: memoryview) -> None:
        if opcode == Opcode.MESSAGE:
            channel_id = _MESSAGE.unpack_from(body)[0]
            self._message(channel_id, bytes(body[_MESSAGE.size:]))
        elif opcode == Opcode.SCHEMA:
            schema = Schema.read(ReadDataStream(io.BytesIO(body)))
            self._schema_data[schema.id] = (schema.name, schema.encoding, schema.data)
        elif opcode == Opcode.CHANNEL:
            channel = Channel.read(ReadDataStream(io.BytesIO(body)))
            if channel.message_encoding != "json":
                self._channels[channel.id] = None  # not ours: its messages are passed over
                return
            if channel.id not in self._channels:
                self.on_channel(channel.topic)
                self._schema_of(channel.topic, channel.schema_id)
            self._channels[channel.id] = (channel.topic, message_checker(channel.topic))

    def _schema_of(self, topic: str, schema_id: int) -> None:
        name, encoding, data = self._schema_data.get(schema_id, ("", "", b""))
        if encoding != "jsonschema":
            return
        try:
            schema = json.loads(data)
        except (ValueError, RecursionError):
            schema = None
        if isinstance(schema, dict):
            self.schemas[topic] = schema
        else:
            self._warnings.append(f"schema {name} of {topic} is not a JSON object (ignored)")

    def _message(self, channel_id: int, data: bytes) -> None:
        channel = self._channels.get(channel_id)
        if channel is None:
            if channel_id not in self._channels:  # its channel record was lost to damage
                key = "?: message on an unknown channel"
                self._bad[key] = self._bad.get(key, 0) + 1
            return
        topic, check = channel
        try:
            msg = json.loads(data)
        except (ValueError, RecursionError):  # UnicodeDecodeError is a ValueError
            msg, problem = None, "not JSON"
        else:
            problem = check(msg)
        if problem is not None:
            key = f"{topic}: {problem}"
            self._bad[key] = self._bad.get(key, 0) + 1
            return
        self._end_t = msg["t"] if self._end_t is None else max(self._end_t, msg["t"])
        if topic == "/config" and self._first_config is None:
            self._first_config = msg
        self.on_message(topic, msg)

    def _finish(self, skipped_records: int, skipped_bytes: int, tail: int, stopped: str, complete: bool) -> None:
        self._configuration()
        self.damage = LogDamage(
            skipped_records=skipped_records,
            skipped_bytes=skipped_bytes,
            tail_bytes=tail,
            gaps=tuple(self._gaps),
            truncated=not complete,
            end_t=self._end_t,
            stopped=stopped,
            bad_messages=dict(self._bad),
            warnings=tuple(self._warnings),
        )

    def _configuration(self) -> None:
        """Config and version: from the metadata, else from the first ``/config`` message."""
        meta = self.metadata.get(METADATA_NAME, {})
        first = self._first_config or {}
        config = first.get("config") if isinstance(first.get("config"), dict) else None
        if "config" in meta:
            try:
                parsed = json.loads(meta["config"])
            except (ValueError, RecursionError):
                parsed = None
            if isinstance(parsed, dict):
                config = parsed
            else:
                fallback = "used the /config message" if config is not None else "no /config message either"
                self._warnings.append(f"metadata config is not a JSON object ({fallback})")
        self.config = config
        version = meta.get("software_version", first.get("software_version"))
        self.software_version = version if isinstance(version, str) else None


def _chunk_records(body: memoryview) -> list[tuple[int, memoryview]]:
    """The records inside a chunk, after checking its size, decompression and CRC (else ValueError)."""
    _, _, size, crc = _CHUNK.unpack_from(body)
    (name_len,) = struct.unpack_from("<I", body, _CHUNK.size)
    at = _CHUNK.size + 4
    compression = bytes(body[at:at + name_len]).decode()
    at += name_len
    (data_len,) = struct.unpack_from("<Q", body, at)
    data = body[at + 8:at + 8 + data_len]
    if len(data) != data_len:
        raise ValueError("chunk data runs past its record")
    if size > MAX_RECORD_BYTES:
        raise ValueError(f"chunk claims {size} bytes uncompressed")
    raw = _decompress(compression, bytes(data), size)
    if len(raw) != size:
        raise ValueError(f"chunk holds {len(raw)} bytes, its header says {size}")
    if crc != 0 and zlib.crc32(raw) != crc:
        raise ValueError("chunk CRC mismatch")
    records = []
    view, at = memoryview(raw), 0
    while at < size:
        opcode, length = _HEADER.unpack_from(view, at)
        at += _HEADER.size
        if length > size - at:
            raise ValueError("record runs past the end of its chunk")
        records.append((opcode, view[at:at + length]))
        at += length
    return records


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    # Bounded by the size the header gives: a corrupt stream cannot expand without limit.
    if compression == "":
        return data
    if compression == "lz4":
        return lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=size + 1)
    if compression == "zstd":
        declared = zstandard.frame_content_size(data)
        if declared > size:
            raise ValueError(f"zstd frame claims {declared} bytes, the chunk {size}")
        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size + 1)
    raise ValueError(f"unknown chunk compression {compression!r}")


def replay_mocap(log: "str | Path | LogData", *, time_offset: float = 0.0) -> Any:
    """A ``ReplayMocap`` pose source over a flight log's ``/mocap`` topic (``ReplayError`` names the file)."""
    from cfknode.mocap.replay import ReplayError, ReplayMocap

    data = log if isinstance(log, LogData) else read_log(log)
    try:
        require_messages(data, ("/mocap",))
    except LogError as exc:
        raise ReplayError(str(exc)) from None
    return ReplayMocap.from_messages(data.topic("/mocap"), name=str(data.path), time_offset=time_offset)
