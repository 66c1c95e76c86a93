"""Ctrl-C in a terminal reaches the whole process group, the online trainer included: only the
flight process acts on it. A real `cfknode fly --online` in its own process group, a real SIGINT
to the group: the flight lands, the trainer neither prints a traceback nor counts as a crash, and
no trainer is started during the landing.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cfknode.app.logs.writer import LogError, read_log

WAIT_S = 300.0  # generous: torch's import and a shared machine; the flight itself takes seconds


def _events(logs: Path) -> list[str]:
    for path in logs.glob("*.mcap"):
        try:
            return [m["text"] for m in read_log(path).topic("/events")]
        except LogError:
            return []
    return []


def test_sigint_to_the_process_group_lands_without_a_trainer_crash(tmp_path):
    logs = tmp_path / "logs"
    cmd = [sys.executable, "-m", "cfknode", "fly", "--headless", "--json", "--online", "--log-dir", str(logs),
           "--set", f"safety.estop_dir={tmp_path / 'estop'}", "--set", "trajectory.kind=hover",
           "--set", "trajectory.duration=60", "--set", "online.trainer_timeout=60"]
    # A session of its own: the group's Ctrl-C must not reach pytest.
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + WAIT_S
        while not any("TAKEOFF -> TRACK" in e for e in _events(logs)):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "no take-off"
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in the terminal does
        out, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert proc.returncode == 1, err
    extra = json.loads(out)["extra"]
    assert extra["outcome"].startswith("landed: Ctrl-C (SIGINT) at "), extra["outcome"]
    assert extra["trainer_crashes"] == 0 and extra["trainer_restarts"] == 0
    assert extra["vehicle_after_shutdown"]["motors"] == [0, 0, 0, 0]
    log = read_log(json.loads(out)["log_path"])
    assert not log.truncated
    assert not {m["event"] for m in log.topic("/model")} & {"crash", "restart"}


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def test_the_trainer_process_ignores_stop_signals():
    """The trainer alone, sent each stop signal before and after its start-up: it stays up, and
    it stops when its parent closes it. One trainer takes all three (a start costs seconds of torch import)."""
    from cfknode.app.config import load_config
    from cfknode.app.learning import trainer_settings
    from cfknode.flight.learning.trainer_client import TrainerClient

    client = TrainerClient(trainer_settings(load_config(overrides={"online.enabled": True})), timeout=60.0)
    client.start()
    try:
        for sig in STOP_SIGNALS:
            os.kill(client.pid, sig)  # during start-up (the torch import)
        assert client.wait_ready(WAIT_S)
        for sig in STOP_SIGNALS:
            os.kill(client.pid, sig)
            time.sleep(0.2)
            assert client.poll(0.0) is None and client.state == "idle", signal.Signals(sig).name
    finally:
        client.close()
    assert client.state == "stopped"
