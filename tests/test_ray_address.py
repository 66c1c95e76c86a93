"""``--executor ray --address``: an address where no Ray cluster answers gives one line and exit
status 2 in bounded time (the probe), and the command stops on a signal while it waits."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
from contextlib import contextmanager
from typing import Callable, Iterator

import pytest

from cfknode.app.bench.ray_probe import RayAddressError, probe_ray, split_address


@contextmanager
def listener(reply: Callable[[socket.socket], None] | None,
             connected: threading.Event | None = None) -> Iterator[int]:
    """A TCP server on a free port; each connection gets ``reply`` (None: accepted, never answered)
    and sets ``connected``."""
    srv = socket.create_server(("127.0.0.1", 0))
    held: list[socket.socket] = []
    stop = threading.Event()

    def serve() -> None:
        srv.settimeout(0.1)
        while not stop.is_set():
            try:
                conn, _ = srv.accept()
            except OSError:
                continue
            held.append(conn)
            if connected is not None:
                connected.set()
            if reply is not None:
                reply(conn)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield srv.getsockname()[1]
    finally:
        stop.set()
        thread.join()
        for conn in held:
            conn.close()
        srv.close()


def _grpc(conn: socket.socket) -> None:
    conn.recv(64)
    conn.sendall(bytes([0, 0, 0, 4, 0, 0, 0, 0, 0]))  # a server's SETTINGS frame, as every HTTP/2 server sends


def _http1(conn: socket.socket) -> None:
    conn.recv(64)
    conn.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")


def _free_port() -> int:
    with socket.create_server(("127.0.0.1", 0)) as s:
        return s.getsockname()[1]


def test_addresses_are_split_into_host_and_port():
    assert split_address("10.0.0.5:6380") == ("10.0.0.5", 6380)
    assert split_address("head") == ("head", 6379)
    assert split_address("ray://head") == ("head", 10001)
    assert split_address("ray://head:10002/") == ("head", 10002)
    assert split_address("[::1]:6379") == ("::1", 6379)
    assert split_address("auto") is None and split_address("local") is None
    for bad in ("head:0", "head:99999", "head:x", ":6379"):
        with pytest.raises(RayAddressError):
            split_address(bad)


def test_a_grpc_server_passes_and_anything_else_is_refused_in_one_line():
    with listener(_grpc) as port:
        probe_ray(f"127.0.0.1:{port}", timeout=5.0)
    with listener(_http1) as port, pytest.raises(RayAddressError, match="not a Ray cluster"):
        probe_ray(f"127.0.0.1:{port}", timeout=5.0)
    with pytest.raises(RayAddressError, match="no Ray cluster there"):
        probe_ray(f"127.0.0.1:{_free_port()}", timeout=5.0)


def test_a_silent_listener_is_given_up_on_after_the_timeout():
    with listener(None) as port, pytest.raises(RayAddressError, match="no Ray cluster answered within 0.3 s") as err:
        probe_ray(f"127.0.0.1:{port}", timeout=0.3)
    assert "\n" not in str(err.value)


def _fly(address: str, tmp_path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "cfknode", "fly", "--fleet", "2", "--executor", "ray", "--address", address,
         "--headless", "--log-dir", str(tmp_path), "--set", f"safety.estop_dir={tmp_path / 'estop'}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_the_cli_refuses_an_unreachable_address_with_exit_status_2(tmp_path):
    pytest.importorskip("ray")
    proc = _fly(f"127.0.0.1:{_free_port()}", tmp_path)
    out, err = proc.communicate(timeout=300)
    lines = err.strip().splitlines()
    assert proc.returncode == 2 and "Traceback" not in err
    assert lines[-1].startswith("cfknode: error: take-off refused: --address 127.0.0.1:")
    assert "no Ray cluster" in lines[-1]


def test_sigterm_stops_the_command_while_it_waits_on_the_address(tmp_path):
    pytest.importorskip("ray")
    connected = threading.Event()
    with listener(None, connected) as port:
        proc = _fly(f"127.0.0.1:{port}", tmp_path)
        assert connected.wait(300), proc.communicate()  # it has reached the address and waits for an answer
        os.kill(proc.pid, signal.SIGTERM)
        proc.communicate(timeout=300)
    assert proc.returncode in (-signal.SIGTERM, 128 + signal.SIGTERM)
