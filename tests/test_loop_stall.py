"""A ``--realtime`` flight whose loop thread is blocked for 4 s, through the real cflib path (sim://).

What the vehicle did is read on the simulator's side, after every plant step, stamped with
simulated time; nothing here asserts a wall-clock duration. The radio's TX thread is the
watchdog: within 0.2 s of the block the vehicle flies a level, descending hold, and its motors
are off within the firmware's commander-watchdog time (2 s, docs/hardware.md#commander-watchdog).
A stop signal during the block reaches the flight through the signal relay and stops it sooner.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.app.mission import run_flight
from cfknode.safety.watchdogs import tilt_deg
from cfknode.sim_backend.link_driver import lookup

# Real-time flights through the sim:// link in their own threads (the same marks as tests/speeds.py).
pytestmark = [pytest.mark.flight, pytest.mark.process, pytest.mark.slow]

BLOCK_AT = 2.0  # s of flight time: hovering at 1 m
BLOCK_S = 4.0
LEVEL_WITHIN = 0.2  # s after the block starts
FIRMWARE_LOCK_S = 2.0  # the commander watchdog's lock time
FLYING = ("TRACK", "LAND")  # hovering, or (on a machine too busy to keep up) landing from there

# The geometric controller and the supervisor's other watchdogs at their most patient: on a loaded
# machine a slow MPC, a late mocap frame or a missed deadline would land the flight before the
# block for reasons of their own; this is about the radio, not them.
HOVER = {
    "sim.realtime": True,
    "controller.kind": "geometric",
    "safety.overrun_ticks": 10_000,
    "safety.mocap_hold_s": 1.0,
    "safety.mocap_stop_s": 5.0,
    "safety.link_silence_s": 2.0,
    "safety.tracking_error_s": 5.0,
    "trajectory.kind": "hover",
    "trajectory.height": 1.0,
    "trajectory.takeoff_duration": 1.0,
    "trajectory.settle_duration": 0.2,
    "trajectory.duration": 8.0,
    "trajectory.land_duration": 1.0,
}


@dataclass
class Sample:
    t: float
    p: np.ndarray
    v: np.ndarray
    tilt: float
    motors: tuple[int, ...]
    setpoint: Any  # the firmware's active setpoint (after its own supervisor's override)


@dataclass
class Blocker:
    """A tick observer that blocks the loop's thread once, and records the simulated vehicle."""

    uri: str
    signals: int = 0  # SIGTERMs sent during the block, from another thread
    sim: Any = None
    t0: float = float("nan")  # simulated time when the block began
    t_signal: float = float("nan")
    state_at_block: str = ""
    samples: list[Sample] = field(default_factory=list)

    def on_tick(self, info: Any) -> None:
        if self.sim is None:
            self.sim = lookup(self.uri).sim
            self.sim.add_step_observer(self._record)
        if info.t < BLOCK_AT or not np.isnan(self.t0):  # once
            return
        self.t0, self.state_at_block = self.sim.t, info.supervisor_state
        sender = threading.Thread(target=self._send_signals) if self.signals else None
        if sender is not None:
            sender.start()
        time.sleep(BLOCK_S)  # the loop's thread is stuck here; nothing on it runs
        if sender is not None:
            sender.join()

    def _record(self, t: float, state: np.ndarray) -> None:
        fw = self.sim.firmware
        self.samples.append(Sample(t, state[:3].copy(), state[3:6].copy(), tilt_deg(state[6:10]),
                                   tuple(fw.motor_commands), fw.active_setpoint))

    def _send_signals(self) -> None:
        while self.sim.t < self.t0 + 0.3:  # simulated time, whatever the machine's load
            time.sleep(0.005)
        self.t_signal = self.sim.t
        for _ in range(self.signals):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.02)


@pytest.fixture
def no_sigterm_kill():
    """A SIGTERM that came after the flight's relay had gone must not end pytest."""
    previous = signal.signal(signal.SIGTERM, lambda *a: None)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _fly(tmp_path: Any, blocker: Blocker, **overrides: Any) -> tuple[Any, int]:
    cfg = load_config(overrides={**HOVER, "log.dir": str(tmp_path), **overrides})
    blocker.uri = cfg.radio.uri
    hold: list[int] = []
    result = run_flight(cfg, name_hint="stall", observers=[blocker],
                        on_supervisor=lambda sup: hold.append(int(sup.blind_setpoint.thrust)))
    return result, hold[0]


def _motors_off_at(blocker: Blocker) -> float:
    off = [s.t for s in blocker.samples if s.t >= blocker.t0 and s.motors == (0, 0, 0, 0)]
    assert off, "the motors never stopped during the block"
    return off[0]


def test_a_stalled_loop_holds_level_and_descending_then_stops_the_motors(tmp_path, no_sigterm_kill):
    blocker = Blocker(uri="")
    result, hold_thrust = _fly(tmp_path, blocker)
    t0 = blocker.t0
    assert blocker.state_at_block in FLYING, result.record.events
    at_block = next(s for s in blocker.samples if s.t >= t0)
    assert at_block.p[2] > 0.6, result.record.events  # in the air when the loop stopped
    t_off = _motors_off_at(blocker)
    assert t_off - t0 <= FIRMWARE_LOCK_S
    held = [s for s in blocker.samples if t0 + LEVEL_WITHIN <= s.t < t_off]
    assert len(held) > 50  # the hold lasted (1 s by default), and was recorded every plant step
    for s in held:
        sp = s.setpoint
        assert (sp.roll, sp.pitch, sp.yaw_rate) == (0.0, 0.0, 0.0) and 0 < sp.thrust <= hold_thrust, (s.t, sp)
        assert s.tilt < 5.0, (s.t, s.tilt)
        assert s.v[2] < 0.05, (s.t, s.v)  # not climbing
    assert held[-1].v[2] < -0.2 and held[-1].p[2] < at_block.p[2] - 0.1  # descending
    assert np.linalg.norm(held[-1].p[:2] - at_block.p[:2]) < 0.15  # no drift on a stale tilt
    after = [s for s in blocker.samples if s.t >= t_off]
    assert all(s.motors == (0, 0, 0, 0) for s in after)  # latched: the loop coming back restarts nothing
    outcome = result.outcome
    assert outcome.cause == "loop_stall_stop", outcome.message
    assert "the flight loop stalled" in outcome.message
    assert result.summary.extra["safety_cause"] == "loop_stall_stop"
    assert any("the flight loop stalled (no setpoint for" in e for e in result.record.events)


def test_a_signal_during_the_block_still_stops_the_vehicle(tmp_path, no_sigterm_kill):
    # The stall alone would stop the motors only at 1.9 s: two SIGTERMs at 0.3 s do it sooner.
    blocker = Blocker(uri="", signals=2)
    result, _ = _fly(tmp_path, blocker, **{"radio.stale_stop_s": 1.9})
    t0 = blocker.t0
    assert blocker.state_at_block in FLYING, result.record.events
    t_off = _motors_off_at(blocker)
    assert blocker.t_signal <= t_off < t0 + 1.5, (t0, blocker.t_signal, t_off)
    assert all(s.motors == (0, 0, 0, 0) for s in blocker.samples if s.t >= t_off)
    assert result.outcome.cause == "sigterm_stop", result.outcome.message
    assert result.outcome.message.startswith("motors stopped: second SIGTERM")
