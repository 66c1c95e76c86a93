"""Whether a Ray cluster answers at an address, in bounded time, before ``ray.init`` is asked.

``ray.init(address=...)`` retries an address where nothing listens for minutes, inside Ray's
own code, where stop signals wait. A cluster's head (the GCS, or the Ray Client server for
``ray://``) is a gRPC server: it answers the HTTP/2 connection preface with a SETTINGS frame at
once. So the probe connects, sends the preface, and waits for that frame, ``timeout`` at most.
"""

from __future__ import annotations

import socket

DEFAULT_PORT = 6379  # Ray's GCS port when the address names none
CLIENT_PORT = 10001  # Ray Client's port for ray://HOST
PROBE_TIMEOUT_S = 5.0
_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])  # + an empty SETTINGS frame
_SETTINGS = 4


class RayAddressError(ConnectionError):
    """No Ray cluster answers at the address; the message is one line."""


def split_address(address: str) -> tuple[str, int] | None:
    """(host, port) of a cluster address; None for the addresses Ray resolves itself (auto, local)."""
    text = address.strip()
    if text in ("auto", "local"):
        return None
    client = text.startswith("ray://")
    text = text.removeprefix("ray://").rstrip("/")
    host, sep, port = text.rpartition(":")
    if not sep or "]" in port:  # no port (an IPv6 literal's colons are inside its brackets)
        host, port = text, ""
    host = host.strip("[]")
    if not host:
        raise RayAddressError(f"--address {address!r}: give HOST:PORT (or ray://HOST:PORT)")
    if not port:
        return host, CLIENT_PORT if client else DEFAULT_PORT
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise RayAddressError(f"--address {address!r}: the port must be a number from 1 to 65535")
    return host, int(port)


def probe_ray(address: str, timeout: float = PROBE_TIMEOUT_S) -> None:
    """Raise ``RayAddressError`` unless a gRPC server (a Ray head) answers at ``address`` within ``timeout`` s."""
    target = split_address(address)
    if target is None:
        return
    host, port = target
    try:
        with socket.create_connection((host, port), timeout=timeout) as sock:
            sock.settimeout(timeout)
            sock.sendall(_PREFACE)
            head = _read(sock, 9)
    except socket.timeout:
        raise RayAddressError(f"--address {address}: no Ray cluster answered within {timeout:g} s") from None
    except OSError as exc:
        raise RayAddressError(f"--address {address}: no Ray cluster there ({exc.strerror or exc})") from None
    if len(head) < 9 or head[3] != _SETTINGS:
        raise RayAddressError(f"--address {address}: something listens there, but not a Ray cluster (no gRPC answer)")


def _read(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        part = sock.recv(n - len(data))
        if not part:
            break
        data += part
    return data


__all__ = ["PROBE_TIMEOUT_S", "RayAddressError", "probe_ray", "split_address"]
