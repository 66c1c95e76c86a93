"""The supervisor's side of a stalled loop: it arms the radio's hold, passes stop signals on to
the radio at once, and acts on what the radio reports (driven tick by tick with fakes)."""

from __future__ import annotations

import asyncio
import os
import signal
import threading
import time
from collections import deque
from types import SimpleNamespace

from cfknode.app.fleet import flight as fleet
from cfknode.app.fleet.drone_actor import DroneActor
from cfknode.app.mission import build_supervisor
from cfknode.kernel.setpoint import AttitudeSetpoint
from cfknode.safety.supervisor import State
from test_fleet_signals import _coordinator, _Sup
from test_safety_supervisor import FakeRadio, Rig


class GuardedRadio(FakeRadio):
    """A radio that checks its setpoint's age, as the threaded CflibRadio does."""

    def __init__(self) -> None:
        super().__init__()
        self.hold: AttitudeSetpoint | None = None
        self.listener = None
        self.signals: list[int] = []

    def set_stale_hold(self, hold: AttitudeSetpoint, listener) -> None:
        self.hold, self.listener = hold, listener

    def stop_signal(self, count: int) -> None:
        self.signals.append(count)


def _rig() -> Rig:
    rig = Rig()
    rig.radio = GuardedRadio()
    rig.sup = build_supervisor(rig.cfg, rig.radio, trajectory=rig.traj, log=rig.log, deadlines_apply=True)
    rig.to_track()
    return rig


def test_the_radio_holds_on_the_blind_setpoint_and_reports_to_the_supervisor():
    rig = _rig()
    assert rig.radio.hold == rig.sup.blind_setpoint
    assert rig.radio.listener == rig.sup.loop_stalled


def test_stop_signals_reach_the_radio_at_once_not_at_the_next_tick():
    rig = _rig()
    rig.sup.interrupt("SIGTERM")
    rig.sup.interrupt("SIGINT")
    assert rig.radio.signals == [1, 2]


def test_a_short_stall_is_logged_and_the_flight_goes_on():
    rig = _rig()
    rig.radio.listener("hold", 0.043)
    rig.radio.listener("resumed", 0.2)
    rig.tick()
    assert rig.sup.state is State.TRACK
    texts = [m["text"] for m in rig.log.topic("/events")]
    assert any(t.startswith("the flight loop stalled (no setpoint for 43 ms)") for t in texts)


def test_a_loop_gone_half_a_second_lands_once_it_is_back():
    rig = _rig()
    rig.radio.listener("hold", 0.05)
    rig.radio.listener("resumed", 0.6)
    rig.tick()
    outcome = rig.sup.outcome()
    assert rig.sup.state is State.LAND and outcome.cause == "loop_stall"
    assert "the flight loop stalled for 0.60 s" in outcome.message


def test_the_radio_stopping_the_motors_ends_in_emergency():
    rig = _rig()
    rig.radio.listener("hold", 0.05)
    rig.radio.listener("stop", 1.01)
    rig.tick()
    assert rig.sup.state is State.EMERGENCY and rig.sup.outcome().cause == "loop_stall_stop"
    assert rig.radio.setpoints[-1].thrust == 0


def test_a_ray_actor_passes_a_signal_to_its_supervisor_without_waiting_for_a_tick():
    actor = object.__new__(DroneActor)  # the routing only: no Ray runtime
    actor._inbox, actor._sup = deque(), None
    actor.interrupt("SIGTERM")  # before take-off: queued for the first tick
    assert list(actor._inbox) == [("interrupt", ("SIGTERM",))]
    actor._sup = sup = _Sup()
    actor.interrupt("SIGHUP")
    assert sup.signals == ["SIGHUP"] and len(actor._inbox) == 1


def test_a_fleet_gets_a_stop_signal_while_its_loops_thread_is_blocked(tmp_path, monkeypatch):
    coord, sups, _ = _coordinator(tmp_path)
    blocked = threading.Event()
    seen_while_blocked: list[bool] = []
    for sup in sups:
        def record(name: str, sup=sup) -> None:
            seen_while_blocked.append(blocked.is_set())
            sup.signals.append(name)
        sup.interrupt = record

    async def stuck_loop(p: SimpleNamespace) -> str:
        await asyncio.sleep(0)
        if p.name == "cf1":  # blocks the event loop's thread, so every drone's loop with it
            blocked.set()
            threading.Thread(target=os.kill, args=(os.getpid(), signal.SIGTERM)).start()
            deadline = time.monotonic() + 60.0
            while len(seen_while_blocked) < 2 and time.monotonic() < deadline:
                time.sleep(0.01)  # no await: nothing else on this thread runs meanwhile
            blocked.clear()
        return p.name

    monkeypatch.setattr(fleet, "fly", stuck_loop)
    previous = signal.signal(signal.SIGTERM, lambda *a: None)  # one that came too late must not end pytest
    try:
        drones = [SimpleNamespace(clock=SimpleNamespace()) for _ in sups]
        parts = [SimpleNamespace(name="cf1"), SimpleNamespace(name="cf2")]
        assert asyncio.run(fleet._gather(drones, parts, coord)) == ["cf1", "cf2"]
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert [s.signals for s in sups] == [["SIGTERM"], ["SIGTERM"]]
    assert seen_while_blocked == [True, True]
