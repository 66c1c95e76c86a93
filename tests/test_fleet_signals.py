"""SIGTERM and SIGHUP end a fleet flight as they end a single flight: every drone's supervisor
gets the signal (the first lands them all, a second stops them all), the log is complete with
the events, and the exit status is the single flight's (1 once the fleet has a coordinator)."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from cfknode.flight.controller import TickInfo
from cfknode.safety.process_signals import ProcessSignals
from fakes import finish_json, wait_for_log_events

from cfknode.app.fleet import flight as fleet
from cfknode.app.config import load_config
from cfknode.app.fleet.flight import FleetCoordinator, drone_configs
from cfknode.app.logs.writer import read_log
from cfknode.kernel.setpoint import AttitudeSetpoint

WAIT_S = 240.0  # generous: the machine is shared; the flights themselves take seconds
NAMES = ("cf1", "cf2")
EVENTS = [f"/{n}/events" for n in NAMES]  # every drone's


class _Sup:
    def __init__(self) -> None:
        self.signals: list[str] = []
        self.lands: list[str] = []
        self.cause = ""

    def interrupt(self, signal_name: str = "SIGINT") -> None:
        self.signals.append(signal_name)

    def request_land(self, reason: str, cause: str) -> None:
        self.lands.append(cause)

    def snapshot(self):
        return SimpleNamespace(cause=self.cause)


class _Log:
    def __init__(self) -> None:
        self.events: list[tuple[str, float, dict]] = []

    def write(self, topic: str, t: float, msg: dict) -> None:
        self.events.append((topic, t, msg))


def _coordinator(tmp_path: Path) -> tuple[FleetCoordinator, list[_Sup], _Log]:
    cfg = load_config(None, {"fleet.size": 2, "log.dir": str(tmp_path), "safety.estop_dir": str(tmp_path / "estop")})
    names, _, refs = drone_configs(cfg)
    sups, log = [_Sup(), _Sup()], _Log()
    return FleetCoordinator(cfg, names, sups, refs, log), sups, log


def _tick(t: float, state: str) -> TickInfo:
    est = SimpleNamespace(p=np.array([0.5, 0.0, 1.0]))
    return TickInfo(t, est, np.zeros(3), np.zeros(3), np.zeros(3), AttitudeSetpoint(0, 0, 0, 0), "mpc", 0.0, 0.0,
                    False, 0, state)


def test_a_stop_signal_reaches_every_supervisor_and_is_logged_at_the_next_tick(tmp_path):
    coord, sups, log = _coordinator(tmp_path)
    coord.on_tick(0, _tick(3.0, "TRACK"))
    coord.interrupt("SIGTERM")
    assert [s.signals for s in sups] == [["SIGTERM"], ["SIGTERM"]]
    assert log.events == []  # a signal handler never writes the log
    sups[0].cause = "sigterm"
    coord.on_tick(0, _tick(3.1, "LAND"))
    texts = [m["text"] for _, _, m in log.events]
    assert texts == ["SIGTERM: every drone lands; another SIGTERM (or Ctrl-C) stops them all"]
    assert log.events[0][1] == pytest.approx(3.1) and log.events[0][2]["source"] == "fleet"
    assert sups[1].lands == []  # every drone got the signal: not a fault of cf1's for the others
    coord.interrupt("SIGHUP")
    coord.log_signals(3.2)
    assert log.events[-1][2]["text"] == "SIGHUP (terminal closed) again: every drone stops its motors"
    assert [s.signals for s in sups] == [["SIGTERM", "SIGHUP"], ["SIGTERM", "SIGHUP"]]


def test_the_fleet_loop_routes_every_stop_signal_to_all_and_gives_them_back(tmp_path, monkeypatch):
    # The flight loops replaced by ones that, as flight.loop.fly with FlightParts.signals off,
    # leave the stop signals to the fleet: its routing holds while any loop runs, also after
    # one has ended, and ProcessSignals must have them again afterwards.
    coord, sups, _ = _coordinator(tmp_path)
    ended: list[str] = []

    async def loop_of(p: SimpleNamespace) -> str:
        for k in range(p.ticks):
            await asyncio.sleep(0.01)
            if k in p.send:
                assert p.send[k][0] <= set(ended)  # the loops that must have ended by now
                os.kill(os.getpid(), p.send[k][1])
        ended.append(p.name)
        return p.name

    monkeypatch.setattr(fleet, "fly", loop_of)
    drones = [SimpleNamespace(clock=SimpleNamespace()) for _ in NAMES]
    # cf1 gets SIGTERM while both fly, then SIGHUP once cf2's loop has ended and given them back.
    parts = [SimpleNamespace(name="cf1", supervisor=sups[0], ticks=30,
                             send={2: (set(), signal.SIGTERM), 15: ({"cf2"}, signal.SIGHUP)}),
             SimpleNamespace(name="cf2", supervisor=sups[1], ticks=5, send={})]
    with ProcessSignals() as signals:
        signals.route(coord)
        assert asyncio.run(fleet._gather(drones, parts, coord)) == ["cf1", "cf2"]
        assert [s.signals for s in sups] == [["SIGTERM", "SIGHUP"], ["SIGTERM", "SIGHUP"]]
        assert signals.received == []  # the fleet's loop had them, not the process-wide handler
        os.kill(os.getpid(), signal.SIGTERM)  # after the loops (the hand-back): ProcessSignals routes it
        time.sleep(0.01)
        assert signals.received == ["SIGTERM"]
        assert [s.signals[-1] for s in sups] == ["SIGTERM", "SIGTERM"]


def _start(tmp_path: Path, *sets: str) -> subprocess.Popen[str]:
    """A two-drone lockstep fleet on the circle that would fly 10 s of pattern, headless, JSON."""
    cmd = [sys.executable, "-m", "cfknode", "fly", "--fleet", "2", "--headless", "--json",
           "--log-dir", str(tmp_path / "logs"), "--set", f"safety.estop_dir={tmp_path / 'estop'}",
           "--set", "trajectory.duration=10", "--set", "trajectory.takeoff_duration=1.5",
           *(a for s in sets for a in ("--set", s))]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_a_stop_signal_in_flight_lands_every_drone(tmp_path, sig):
    proc = _start(tmp_path)
    wait_for_log_events(proc, tmp_path / "logs", EVENTS, "TAKEOFF -> TRACK", WAIT_S)
    proc.send_signal(sig)
    code, result, err = finish_json(proc, WAIT_S)
    text = "SIGTERM" if sig is signal.SIGTERM else "SIGHUP (terminal closed)"
    assert code == 1, err  # landed safely, but the mission was cut short: as a single flight
    assert "Traceback" not in err
    for name in NAMES:
        drone = result["drones"][name]
        extra = drone["extra"]
        assert drone["outcome"].startswith(f"landed: {text} at "), drone["outcome"]
        assert extra["safety_state"] == "LANDED" and extra["safety_cause"] == sig.name.lower()
        assert extra["firmware_after_shutdown"] == "landed"
        assert extra["vehicle_after_shutdown"]["motors"] == [0, 0, 0, 0]
        assert extra["vehicle_after_shutdown"]["on_ground"]
    assert not any("on_fault" in e for e in result["events"])  # no drone's landing taken for a fault
    assert any(e.endswith(f"{text}: every drone lands; another {sig.name} (or Ctrl-C) stops them all")
               for e in result["events"])
    log = read_log(result["log"])
    assert not log.truncated
    for name in NAMES:
        assert any(f"TRACK -> LAND: {text}" in m["text"] for m in log.topic(f"/{name}/events"))
        assert log.topic(f"/{name}/summary")[0]["extra"]["outcome"] == result["drones"][name]["outcome"]
    assert [m["source"] for m in log.topic("/events")] == ["fleet"]
    assert log.topic("/summary")[0]["outcomes"] == {n: result["drones"][n]["outcome"] for n in NAMES}


def test_a_second_sigterm_stops_every_drone(tmp_path):
    # A slow landing from 1 m, so the second signal arrives while both are under way.
    proc = _start(tmp_path, "trajectory.height=1.0", "safety.land_speed=0.1")
    wait_for_log_events(proc, tmp_path / "logs", EVENTS, "TAKEOFF -> TRACK", WAIT_S)
    proc.send_signal(signal.SIGTERM)
    wait_for_log_events(proc, tmp_path / "logs", EVENTS, "TRACK -> LAND: SIGTERM", WAIT_S)
    proc.send_signal(signal.SIGTERM)
    code, result, err = finish_json(proc, WAIT_S)
    assert code == 1, err
    assert "Traceback" not in err
    for name in NAMES:
        drone = result["drones"][name]
        assert drone["extra"]["safety_state"] == "EMERGENCY" and drone["extra"]["safety_cause"] == "sigterm_stop"
        assert drone["outcome"].startswith("motors stopped: second SIGTERM at "), drone["outcome"]
        assert drone["extra"]["vehicle_after_shutdown"]["motors"] == [0, 0, 0, 0]
    assert any(e.endswith("SIGTERM again: every drone stops its motors") for e in result["events"])
    assert not read_log(result["log"]).truncated
