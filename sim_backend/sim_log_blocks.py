"""Log blocks as the firmware's log service keeps them: created, started and emitted on sim time."""

from __future__ import annotations

import errno
import struct
import threading

from cfknode.sim_backend.crtp_codes import (
    LOG_APPEND_V2,
    LOG_CREATE_V2,
    LOG_DELETE,
    LOG_RESET,
    LOG_START,
    LOG_STOP,
    pack_clamped,
)
from cfknode.sim_backend.sim_toc import LOG_TOC, LOG_TYPES, EndpointView, LogVariable

_LOG_MAX_BLOCKS = 16  # firmware LOG_MAX_BLOCKS
_LOG_MAX_PAYLOAD = 26  # firmware LOG_MAX_LEN


class _LogBlock:
    """A log block: variables, fetch types, period, next emission."""

    __slots__ = ("block_id", "entries", "period_s", "next_t", "started", "emitted")

    def __init__(self, block_id: int) -> None:
        self.block_id = block_id
        self.entries: list[tuple[LogVariable, str]] = []  # (variable, fetch format)
        self.period_s = 0.0
        self.next_t = 0.0
        self.started = False
        self.emitted = 0  # payloads sent to the host: a lockstep host waits until it has read them all

    def payload_size(self) -> int:
        return sum(struct.calcsize(fmt) for _, fmt in self.entries)


class LogBlocks:
    """One link's log blocks. Settings arrive in the sender's thread, emission in the sim's."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._blocks: dict[int, _LogBlock] = {}
        self.logging = False  # any block started: the per-step check is this one flag

    def clear(self) -> None:
        with self._lock:
            self.logging = False
            self._blocks.clear()

    def settings_reply(self, data: bytearray, now: float) -> bytes | None:
        """Apply a log-settings command; the reply payload, or None for an unknown command."""
        cmd = data[0]
        if cmd == LOG_RESET:
            self.clear()
            return bytes((LOG_RESET, 0, 0))
        block_id = data[1]
        with self._lock:
            if cmd in (LOG_CREATE_V2, LOG_APPEND_V2):
                status = self._add_to_block(cmd, block_id, data[2:])
            elif cmd == LOG_START:
                status = self._start_block(block_id, data[2], now)
            elif cmd == LOG_STOP:
                block = self._blocks.get(block_id)
                status = errno.ENOENT if block is None else 0
                if block is not None:
                    block.started = False
            elif cmd == LOG_DELETE:
                status = errno.ENOENT if self._blocks.pop(block_id, None) is None else 0
            else:
                return None
            self.logging = any(b.started for b in self._blocks.values())
        return bytes((cmd, block_id, status))

    def _add_to_block(self, cmd: int, block_id: int, spec: bytearray) -> int:
        if cmd == LOG_CREATE_V2:
            if block_id in self._blocks:
                return errno.EEXIST
            if len(self._blocks) >= _LOG_MAX_BLOCKS:
                return errno.ENOMEM
            block = _LogBlock(block_id)
        else:
            block = self._blocks.get(block_id)
            if block is None:
                return errno.ENOENT
        if len(spec) % 3 != 0:
            return errno.ENOEXEC  # raw memory addresses: the sim has no memory map
        entries = list(block.entries)
        for i in range(0, len(spec), 3):
            type_byte, ident = spec[i], spec[i + 1] | (spec[i + 2] << 8)
            fetch = LOG_TYPES.get(type_byte & 0x0F)
            if ident >= len(LOG_TOC) or fetch is None:
                return errno.ENOENT
            entries.append((LOG_TOC[ident], fetch))
        block.entries = entries
        if block.payload_size() > _LOG_MAX_PAYLOAD:
            return errno.E2BIG
        self._blocks[block_id] = block
        return 0

    def _start_block(self, block_id: int, period_10ms: int, now: float) -> int:
        block = self._blocks.get(block_id)
        if block is None:
            return errno.ENOENT
        block.period_s = max(period_10ms, 1) * 0.01
        block.next_t = now + block.period_s
        block.started = True
        return 0

    def emitted(self, block_id: int) -> int:
        """How many payloads block ``block_id`` has sent (0 for an unknown block)."""
        with self._lock:
            block = self._blocks.get(block_id)
            return block.emitted if block is not None else 0

    def due_payloads(self, t: float, endpoint: EndpointView) -> list[bytes]:
        """The log-data payloads of each started block that is due at ``t``."""
        out: list[bytes] = []
        with self._lock:
            stamp = int(round(t * 1000.0)) & 0xFFFFFF
            for block in self._blocks.values():
                if not block.started or t < block.next_t - 1e-9:
                    continue
                block.next_t += block.period_s
                if block.next_t <= t:  # fell behind (e.g. started long ago): resync, no burst
                    block.next_t = t + block.period_s
                payload = bytearray((block.block_id, stamp & 0xFF, (stamp >> 8) & 0xFF, stamp >> 16))
                for var, fmt in block.entries:
                    payload += pack_clamped(fmt, var.read(endpoint))
                block.emitted += 1
                out.append(bytes(payload))
        return out
