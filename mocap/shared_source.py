"""One mocap connection for several rigid bodies (a fleet in one lab's mocap volume).

A lab has one motion-capture system, and its SDK serves every rigid body in each frame, so a
fleet opens one connection (``MocapHub.open``) and one reader thread, which hands each frame to
every robot's ``MotioncaptureSource`` by rigid-body name. Each robot's source keeps its own
counters, rate check, latest pose and pose listener (its radio's extpose feed), exactly as when
it reads a connection of its own; only the connection and the thread are shared.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Mapping, Sequence

from cfknode.mocap.motioncapture_source import (
    Connector,
    MotioncaptureSource,
    close_client,
    connect_with_deadline,
    default_connector,
    motioncapture_config,
    sdk_label,
)


class SharedBodySource(MotioncaptureSource):
    """One rigid body of a shared connection: fed by the hub's reader thread, never reading itself."""

    def __init__(self, hub: "MocapHub", rigid_body: str, *, expected_rate_hz: float, label: str) -> None:
        super().__init__(None, rigid_body, expected_rate_hz=expected_rate_hz, label=label)
        self._hub = hub

    def start(self) -> "SharedBodySource":
        return self  # the hub's thread reads for every body

    def reader_alive(self) -> bool:
        return self._hub.reader_alive()

    def close(self) -> None:
        self._stop = True  # the connection is the hub's to close


class MocapHub:
    """One ``motioncapture`` client, one reader thread, a ``SharedBodySource`` per rigid body."""

    def __init__(self, client: Any, bodies: Sequence[str], *, expected_rate_hz: float = 100.0,
                 label: str = "mocap") -> None:
        if len(set(bodies)) != len(bodies):
            raise ValueError(f"rigid bodies must be distinct, got {list(bodies)}")
        self._client = client
        self.label = label
        self.sources: dict[str, SharedBodySource] = {
            name: SharedBodySource(self, name, expected_rate_hz=expected_rate_hz, label=label) for name in bodies}
        self._stop = False
        self._thread = threading.Thread(target=self._run, name=f"mocap-reader {label} (shared)", daemon=True)

    @classmethod
    def open(cls, mocap_type: str, host: str, bodies: Sequence[str], *, timeout: float = 5.0,
             connect: Connector | None = None, expected_rate_hz: float = 100.0,
             mock_bodies: Mapping[str, tuple[float, ...]] | None = None) -> "MocapHub":
        """Connect once (with a deadline: ``MocapError`` naming the type and host) and start reading."""
        cfg = motioncapture_config(mocap_type, host, mock_bodies=mock_bodies, mock_rate_hz=expected_rate_hz)
        connect = connect if connect is not None else default_connector(timeout)
        client = connect_with_deadline(connect, mocap_type, cfg, timeout)
        return cls(client, bodies, expected_rate_hz=expected_rate_hz, label=sdk_label(mocap_type, cfg)).start()

    def start(self) -> "MocapHub":
        self._thread.start()
        return self

    def source(self, name: str) -> SharedBodySource:
        return self.sources[name]

    def reader_alive(self) -> bool:
        return self._thread.is_alive()

    def _run(self) -> None:
        client = self._client
        while not self._stop:
            try:
                client.waitForNextFrame()
                mono = getattr(client, "frame_monotonic", None) or time.monotonic()
                frame = client.rigidBodies
                bodies = {name: frame.get(name) for name in self.sources}
            except Exception as exc:
                if not self._stop:
                    for src in self.sources.values():
                        src.stream_ended(exc)
                return
            for name, src in self.sources.items():
                src.ingest(mono, bodies[name])

    def close(self) -> None:
        self._stop = True
        for src in self.sources.values():
            src.close()
        close_client(self._client, self._thread)


__all__ = ["MocapHub", "SharedBodySource"]
