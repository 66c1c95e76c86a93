"""Test doubles shared by several test modules (plain classes; pytest puts tests/ on sys.path)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Est:
    """The part of a state estimate the online side reads."""

    p: np.ndarray
    v: np.ndarray


@dataclass(frozen=True)
class Tick:
    """What the loop hands its observers after a tick (``flight.loop.TickInfo``'s fields the learner reads)."""

    t: float
    est: Est | None
    acc: np.ndarray
    source: str = "mpc"
    model_version: int = 0
    compute_s: float = 0.0
    supervisor_state: str = ""
    layer: Any = None  # the fast layer's AdaptationEstimate, when one flies
    guarded: bool = False  # the fall guard flew the tick (the thrust dropped under the model)
    saturated: bool = False  # the command was cut by a limit, or the guard flew it


class ListLog:
    """A flight log that keeps messages in memory."""

    def __init__(self) -> None:
        self.messages: list[tuple[str, float, dict[str, Any]]] = []

    def write(self, topic: str, t: float, msg: dict[str, Any]) -> None:
        self.messages.append((topic, t, dict(msg)))

    def topic(self, name: str) -> list[dict[str, Any]]:
        return [m for topic, _, m in self.messages if topic == name]


class RecordingFirmware:
    """The firmware inputs the sim:// link driver calls, recorded as (name, t, *args).

    ``note`` is called on every input and its value kept in ``notes`` (a test records, say, the
    thread that delivered the packet, or whether the simulator's lock was held).
    """

    def __init__(self, note: Callable[[], Any] = lambda: None) -> None:
        self.calls: list[tuple[Any, ...]] = []
        self.notes: list[Any] = []
        self.supervisor_state = "idle"
        self._note = note

    def _record(self, *call: Any) -> None:
        self.notes.append(self._note())
        self.calls.append(call)

    def named(self, name: str) -> list[tuple[Any, ...]]:
        return [c for c in self.calls if c[0] == name]

    def on_rpyt(self, t: float, roll: float, pitch: float, yawrate: float, thrust: int) -> None:
        self._record("rpyt", t, roll, pitch, yawrate, thrust)

    def on_stop(self, t: float) -> None:
        self._record("stop", t)

    def on_notify_setpoint_stop(self, t: float) -> None:
        self._record("notify_stop", t)

    def on_hl_stop(self, t: float) -> None:
        self._record("hl_stop", t)

    def on_extpose(self, t: float, pos: tuple, quat_xyzw: tuple) -> None:
        self._record("extpose", t, pos, quat_xyzw)

    def on_emergency_stop(self, t: float) -> None:
        self._record("estop", t)

    def on_emergency_stop_watchdog(self, t: float) -> None:
        self._record("heartbeat", t)

    def power_off(self, t: float) -> None:
        self._record("power_off", t)

    def power_on(self, t: float) -> None:
        self._record("power_on", t)


def serve_sim(sim: Any, port: int) -> Iterator[tuple[Any, str]]:
    """Serve ``sim`` at ``sim://port`` for the life of a fixture (``yield from serve_sim(...)``)."""
    from cfknode.sim_backend.link_driver import register_simulator, unregister_simulator

    uri = f"sim://{port}"
    register_simulator(uri, sim)
    try:
        yield sim, uri
    finally:
        unregister_simulator(uri)


# A take-off, 1.5 s of pattern and a landing: the shortest whole flight the log tests read back.
SHORT_FLIGHT = {
    "trajectory.duration": 1.5,
    "trajectory.takeoff_duration": 1.0,
    "trajectory.settle_duration": 0.2,
    "trajectory.land_duration": 1.0,
    "trajectory.ramp_duration": 0.4,
}


def wait_for_log_events(proc: Any, logs: Any, topics: list[str], text: str, wait_s: float) -> None:
    """Until the flight log in ``logs`` has an event containing ``text`` on every one of ``topics``
    (events are flushed at once); fails the test after ``wait_s`` or when ``proc`` ends first."""
    import time

    import pytest

    from cfknode.app.logs.writer import LogError, read_log

    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        for path in logs.glob("*.mcap"):
            try:
                log = read_log(path)
            except LogError:
                continue
            if all(any(text in m["text"] for m in log.topic(topic)) for topic in topics):
                return
        time.sleep(0.05)
    proc.kill()
    pytest.fail(f"no event {text!r} on {', '.join(topics)} within {wait_s} s")


def finish_json(proc: Any, wait_s: float) -> tuple[int, dict, str]:
    """Exit status, the JSON it printed on stdout, and its stderr."""
    import json

    out, err = proc.communicate(timeout=wait_s)
    return proc.returncode, json.loads(out), err
