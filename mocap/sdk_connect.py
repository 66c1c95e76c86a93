"""Connecting to a mocap through libmotioncapture (``motioncapture`` on PyPI): the config it
takes, the one error type, and a connect with a deadline.

``connect`` is injectable (``(type, cfg) -> object with waitForNextFrame() and rigidBodies``),
so tests drive the same reader thread with a fake fed by the simulator.
"""

from __future__ import annotations

import threading
from typing import Any, Callable, Mapping

from cfknode.kernel.messages import first_line

MOCAP_TYPES = ("vicon", "optitrack", "qualisys", "vrpn", "mock")
SDK_TYPES = ("vicon", "optitrack", "qualisys", "vrpn")

Connector = Callable[[str, dict[str, str]], Any]


class MocapError(RuntimeError):
    """The mocap could not connect or its stream ended; the message is one line."""


def motioncapture_config(
    mocap_type: str, host: str, *, mock_bodies: Mapping[str, tuple[float, ...]] | None = None,
    mock_rate_hz: float = 100.0,
) -> dict[str, str]:
    """The string dict ``motioncapture.connect`` takes (``src/motioncapture.cpp`` keys; docs/hardware.md#mocap).

    ``host`` may carry a port (``vicon``: ``host:801``, the SDK parses it; ``qualisys``: it
    becomes the ``port`` key). ``mock`` ignores the host and serves ``mock_bodies``
    (name -> x, y, z, qw, qx, qy, qz) as static frames at ``mock_rate_hz``.
    """
    if mocap_type not in MOCAP_TYPES:
        raise MocapError(f"unknown mocap type {mocap_type!r}; use one of {', '.join(MOCAP_TYPES)}")
    if mocap_type == "mock":
        bodies = ";".join(
            f"{name}({','.join(format(float(v), '.9g') for v in values)})"
            for name, values in (mock_bodies or {}).items()
        )
        return {"rigid_bodies": bodies, "frequency": format(float(mock_rate_hz), "g")}
    if not host:
        raise MocapError(f"{mocap_type} needs a host (hardware.mocap_host / --mocap-host)")
    if mocap_type == "qualisys" and ":" in host:
        hostname, port = host.rsplit(":", 1)
        return {"hostname": hostname, "port": port}
    return {"hostname": host}


def connect_with_deadline(connect: Connector, mocap_type: str, cfg: dict[str, str], timeout: float) -> Any:
    """Run ``connect`` in a thread and give up after ``timeout`` with a one-line error."""
    result: dict[str, Any] = {}
    lock = threading.Lock()

    def run() -> None:
        try:
            client = connect(mocap_type, cfg)
        except BaseException as exc:  # handed to the caller's thread
            result["error"] = exc
            return
        with lock:
            abandoned = result.get("abandoned", False)
            result["client"] = client
        if abandoned:  # answered after the caller gave up: nobody will read it
            closer = getattr(client, "release", None) or getattr(client, "close", None)
            if closer is not None:
                closer()

    thread = threading.Thread(target=run, name=f"mocap-connect {mocap_type}", daemon=True)
    thread.start()
    thread.join(timeout)
    with lock:
        if "client" not in result and "error" not in result:
            result["abandoned"] = True
            raise MocapError(no_answer(mocap_type, cfg, timeout))
    error = result.get("error")
    if isinstance(error, MocapError):
        raise error
    if error is not None:
        raise MocapError(f"could not connect to {sdk_label(mocap_type, cfg)}: "
                         f"{first_line(f'{type(error).__name__}: {error}')}") from None
    return result["client"]


def sdk_label(mocap_type: str, cfg: Mapping[str, str]) -> str:
    """``type at host[:port]``, how messages name a mocap."""
    host = cfg.get("hostname")
    if host and cfg.get("port"):
        host = f"{host}:{cfg['port']}"
    return f"{mocap_type} at {host}" if host else mocap_type


def no_answer(mocap_type: str, cfg: Mapping[str, str], timeout: float) -> str:
    return (f"no answer from {sdk_label(mocap_type, cfg)} within {timeout:g} s "
            "(is the mocap software running and streaming, and is the host right?)")
