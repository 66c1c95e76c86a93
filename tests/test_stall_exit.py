"""A flight loop that never returns after the radio stopped the motors for it ends the process:
an event, the log closed (everything recorded kept), one line on stderr, a non-zero exit."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from cfknode.app.logs.writer import read_log
from cfknode.app.stall_exit import EXIT_STATUS, LoopProgress, stall_exit
from test_loop_stall import BLOCK_AT

TESTS = Path(__file__).resolve().parent
HARNESS_GUARD_S = 300.0  # only so a broken build cannot hang the test run; the claim is the exit itself


class _Radio:
    def __init__(self, stops: int = 0, off: bool = False) -> None:
        self.stops, self.off = stops, off
        self.shut = False

    def stats(self) -> SimpleNamespace:
        return SimpleNamespace(stale_stops=self.stops, motors_off=self.off)

    def shutdown(self) -> None:
        self.shut = True


class _Log:
    path = "/tmp/x.mcap"

    def __init__(self) -> None:
        self.events: list[tuple[float, dict]] = []
        self.closed = False

    def write(self, topic: str, t: float, msg: dict) -> None:
        self.events.append((t, msg))

    def close(self) -> None:
        self.closed = True


class _Ticking(LoopProgress):
    """A loop that ticks all the time: its last tick is always now (no thread, so no machine load, decides)."""

    @property
    def wall(self) -> float:
        return time.monotonic()

    @wall.setter
    def wall(self, value: float) -> None:
        pass


def _watch(radio: _Radio, ticking: bool, wait_s: float, *more: _Radio) -> tuple[list[int], _Log]:
    log, progress, left = _Log(), (_Ticking() if ticking else LoopProgress()), []
    progress.on_tick(SimpleNamespace(t=2.0))
    with stall_exit([radio, *more], log, progress, grace_s=0.3, leave=left.append, idle_grace_s=0.3):
        end = time.monotonic() + wait_s
        while time.monotonic() < end and not left:
            time.sleep(0.01)
    return left, log


def test_a_loop_gone_after_the_radio_stopped_the_motors_closes_the_log_and_leaves(capsys):
    radio = _Radio(stops=1)
    left, log = _watch(radio, ticking=False, wait_s=30.0)
    assert left == [EXIT_STATUS] and EXIT_STATUS != 0
    assert log.closed and radio.shut
    (t, msg), = log.events
    assert t == 2.0 and msg["level"] == "error" and "the flight loop has not come back" in msg["text"]
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("cfknode fly: the flight loop hung") and "log closed: /tmp/x.mcap" in err[0]


def test_a_loop_that_ticks_or_motors_the_radio_did_not_stop_never_end_the_process():
    assert _watch(_Radio(stops=1), ticking=True, wait_s=1.0)[0] == []  # stopped once, but the loop is back
    assert _watch(_Radio(stops=0), ticking=False, wait_s=1.0)[0] == []  # a quiet loop, the radio stopped nothing
    assert _watch(_Radio(off=True), ticking=True, wait_s=1.0)[0] == []  # landed, and the loop still ticks
    # One drone of a fleet landed (its motors off), another still flies: the loop is not given up on.
    assert _watch(_Radio(off=True), False, 1.0, _Radio(off=False))[0] == []


def test_a_loop_gone_with_every_motor_already_off_closes_the_log_and_leaves(capsys):
    """Landed (or in its teardown): no stall stop ever comes, and the process must not live forever."""
    radios = (_Radio(off=True), _Radio(off=True))
    left, log = _watch(*radios[:1], False, 30.0, *radios[1:])
    assert left == [EXIT_STATUS] and log.closed and all(r.shut for r in radios)
    (t, msg), = log.events
    assert t == 2.0 and msg["level"] == "error" and "and the motors are off" in msg["text"]
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("cfknode fly: the flight loop hung") and "motors off" in err[0]


_HUNG_FLIGHT = """
import sys, threading
sys.path.insert(0, sys.argv[3])
from test_loop_stall import BLOCK_AT, HOVER
import cfknode.app.stall_exit as stall_exit
from cfknode.app.config import load_config

stall_exit.GRACE_S = 2.0  # the test's patience; the default is 10 s
from cfknode.app.mission import run_flight

class Forever:
    def on_tick(self, info):
        if info.t >= BLOCK_AT:
            threading.Event().wait()  # the loop's thread never comes back

cfg = load_config(overrides={**HOVER, "log.dir": sys.argv[1], "safety.estop_dir": sys.argv[2]})
run_flight(cfg, name_hint="hung", observers=[Forever()])
print("the flight returned")
"""


_HUNG_LANDED = """
import sys, threading
sys.path.insert(0, sys.argv[3])
from test_loop_stall import HOVER
import cfknode.app.stall_exit as stall_exit
from cfknode.app.config import load_config
from cfknode.app.mission import run_flight

stall_exit.IDLE_GRACE_S = 2.0  # the test's patience; the default is 10 s

class Forever:
    def on_tick(self, info):
        if info.supervisor_state == "LANDED":
            threading.Event().wait()  # landed, motors off: the loop's thread never comes back

cfg = load_config(overrides={**HOVER, "trajectory.duration": 2.0, "log.dir": sys.argv[1],
                             "safety.estop_dir": sys.argv[2]})
run_flight(cfg, name_hint="hung", observers=[Forever()])
print("the flight returned")
"""


@pytest.mark.flight
@pytest.mark.process
@pytest.mark.slow
@pytest.mark.parametrize("script", [_HUNG_FLIGHT, _HUNG_LANDED], ids=["in_flight", "landed"])
def test_a_realtime_flight_whose_loop_hangs_forever_exits_with_its_log_readable(tmp_path, script):
    logs = tmp_path / "logs"
    proc = subprocess.run([sys.executable, "-c", script, str(logs), str(tmp_path / "estop"), str(TESTS)],
                          capture_output=True, text=True, timeout=HARNESS_GUARD_S)
    assert proc.returncode == EXIT_STATUS, proc.stderr
    assert "the flight returned" not in proc.stdout
    lines = [line for line in proc.stderr.splitlines() if line.startswith("cfknode fly:")]
    assert len(lines) == 1 and "the flight loop hung" in lines[0] and "log closed:" in lines[0], proc.stderr
    path, = logs.glob("*.mcap")
    log = read_log(path)
    assert not log.truncated  # closed: footer and summary written
    states = log.topic("/state")
    texts = [m["text"] for m in log.topic("/events")]
    if script is _HUNG_FLIGHT:
        assert states and BLOCK_AT - 0.5 < states[-1]["t"] <= BLOCK_AT + 0.1  # recorded up to the hang, kept
        assert "motors stopped by the radio" in lines[0]
    else:  # hung on its last tick, landed: the whole flight is recorded, and no stall stop came first
        assert states and log.array("/state", "p_true")[-1, 2] < 0.05
        assert "motors off" in lines[0]
        assert any("and the motors are off" in t for t in texts), texts
    assert any("the flight loop has not come back" in t for t in texts), texts
