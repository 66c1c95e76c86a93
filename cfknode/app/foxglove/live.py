"""A live view of a flight in Foxglove: a local WebSocket server from ``foxglove-sdk``.

``LiveServer`` owns its own SDK ``Context`` (no process-wide channel state), advertises ``/tf``,
``/scene`` and ``/log`` with Foxglove's standard schemas before take-off, and is a sink for
``FoxgloveView``. Open Foxglove, "Open connection", ``ws://<host>:<port>``. See docs/foxglove.md.
"""

from __future__ import annotations


import contextlib
from typing import Any

import foxglove

from cfknode.app.foxglove.view import SCHEMAS
from cfknode.kernel.errors import ConfigError

DEFAULT_PORT = 8765


class LiveServer:
    """The live server and its channels; use as a context manager (stops the server at exit)."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT) -> None:
        if not 0 <= port <= 65535:
            raise ConfigError(f"--foxglove port must be 0 to 65535, got {port}")
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(name="cfknode", host=host, port=port, context=self._context)
        except Exception as exc:  # the SDK raises its own error types for a busy or unbindable port
            raise ConfigError(f"cannot serve Foxglove on {host}:{port}: {str(exc)[:120]}") from None
        self._channels = {topic: foxglove.Channel(topic, schema=schema, message_encoding="protobuf",
                                                  context=self._context)
                          for topic, schema in SCHEMAS.items()}
        self.messages = 0

    @property
    def port(self) -> int:
        """The bound port (the one asked for, or the system's choice for port 0)."""
        return int(self._server.port)

    def publish(self, topic: str, t: float, data: bytes) -> None:
        self._channels[topic].log(data, log_time=max(0, round(t * 1e9)))
        self.messages += 1

    def close(self) -> None:
        self._server.stop()

    def __enter__(self) -> LiveServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def live_view(port: int | None, console: Any) -> contextlib.AbstractContextManager[LiveServer | None]:
    """The live server ``--foxglove PORT`` asks for, its address printed (a bad port is a ConfigError), or none."""
    if port is None:
        return contextlib.nullcontext(None)
    server = LiveServer(port=port)
    console.print(f"Foxglove live view: ws://127.0.0.1:{server.port} (Open connection in Foxglove)")
    return server
