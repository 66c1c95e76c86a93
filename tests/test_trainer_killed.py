"""A trainer process killed from outside (``kill -9``) while it idles, in a lockstep online flight.

The next round sent to it meets a broken pipe. That must read as a trainer crash, as a crash in
the middle of a round does: counted, restarted within ``online.max_restarts``, the flight goes on.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
from typing import Any

import numpy as np

from cfknode.app.config import load_config
from cfknode.app.learning import trainer_settings
from cfknode.app.mission import run_flight
from cfknode.flight.learning.shared_trainer import SharedTrainer
from cfknode.flight.learning.trainer_client import TrainerFault
from cfknode.models.trainer_process import TrainRequest
from test_online_trainer import window

KILL_AT_S = 1.0  # in the take-off: the trainer is up and idle, no round sent yet


class TrainerKiller:
    """A tick observer that kills every trainer process with SIGKILL at its first tick after ``at``."""

    def __init__(self, at: float) -> None:
        self.at = at
        self.killed: list[int] = []

    def on_tick(self, tick: Any) -> None:
        if self.killed or tick.t < self.at:
            return
        for proc in multiprocessing.active_children():
            if proc.name == "cfknode-trainer":
                os.kill(proc.pid, signal.SIGKILL)
                proc.join(10.0)  # dead before the flight goes on, whatever the machine's load
                self.killed.append(proc.pid)


def test_a_trainer_killed_while_idle_is_counted_and_restarted(tmp_path) -> None:
    cfg = load_config(overrides={
        "log.dir": str(tmp_path), "online.enabled": True, "controller.adaptation": "none",
        "trajectory.duration": 3.0, "trajectory.takeoff_duration": 1.5, "trajectory.settle_duration": 0.5,
        "trajectory.land_duration": 1.5, "trajectory.ramp_duration": 0.5,
    })
    killer = TrainerKiller(KILL_AT_S)
    res = run_flight(cfg, name_hint="killed", observers=[killer])
    s = res.summary.extra
    assert len(killer.killed) == 1
    assert s["trainer_crashes"] == 1 and s["trainer_restarts"] == 1
    assert not s.get("internal_errors")
    assert s["safety_cause"] == "complete" and not s["trainer_failed"]
    # The restarted trainer served rounds after the kill.
    assert res.learner is not None and res.learner.client.pid != killer.killed[0]
    assert any(r.sent_t > KILL_AT_S and r.outcome != "lost" for r in res.learner.rounds)


def test_a_shared_trainer_killed_while_idle_faults_the_round_sent_to_it() -> None:
    """The fleet's shared trainer: the port that sends next gets the crash, not an exception."""
    shared = SharedTrainer(trainer_settings(load_config(overrides={"online.enabled": True})), 30.0, 2)
    try:
        shared.start()
        assert shared.wait_ready(120.0)
        proc = shared.client._proc
        os.kill(proc.pid, signal.SIGKILL)
        proc.join(10.0)
        port = shared.ports[1]
        port.submit(TrainRequest(1, 1, window(np.array([0.0, 0.0, -1.0])), (), None, 0.0))  # meets the broken pipe
        fault = port.poll(30.0)
        assert isinstance(fault, TrainerFault) and fault.kind == "crash" and "code -9" in fault.reason
        assert port.state == "starting"  # the learner restarts it, as after any crash
    finally:
        shared.close()
