"""A flight loop that never returns after the radio stopped the motors for it ends the process:
an event, the log closed (everything recorded kept), one line on stderr, a non-zero exit."""

from __future__ import annotations

import subprocess
import sys
import threading
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
    def __init__(self, stops: int = 0) -> None:
        self.stops = stops
        self.shut = False

    def stats(self) -> SimpleNamespace:
        return SimpleNamespace(stale_stops=self.stops)

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


def _watch(radio: _Radio, ticking: bool, wait_s: float) -> tuple[list[int], _Log]:
    log, progress, left = _Log(), LoopProgress(), []
    progress.t = 2.0
    with stall_exit([radio], log, progress, grace_s=0.3, leave=left.append):
        end = time.monotonic() + wait_s
        while time.monotonic() < end and not left:
            if ticking:
                progress.on_tick(SimpleNamespace(t=2.0))
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


_HUNG_FLIGHT = """
import sys, threading
sys.path.insert(0, sys.argv[3])
from test_loop_stall import BLOCK_AT, HOVER
from cfknode.app.config import load_config
from cfknode.app.mission import run_flight

class Forever:
    def on_tick(self, info):
        if info.t >= BLOCK_AT:
            threading.Event().wait()  # the loop's thread never comes back

cfg = load_config(overrides={**HOVER, "log.dir": sys.argv[1], "safety.estop_dir": sys.argv[2]})
run_flight(cfg, name_hint="hung", observers=[Forever()])
print("the flight returned")
"""


@pytest.mark.flight
@pytest.mark.process
@pytest.mark.slow
def test_a_realtime_flight_whose_loop_hangs_forever_exits_with_its_log_readable(tmp_path):
    logs = tmp_path / "logs"
    proc = subprocess.run([sys.executable, "-c", _HUNG_FLIGHT, str(logs), str(tmp_path / "estop"), str(TESTS)],
                          capture_output=True, text=True, timeout=HARNESS_GUARD_S)
    assert proc.returncode == EXIT_STATUS, proc.stderr
    assert "the flight returned" not in proc.stdout
    lines = [line for line in proc.stderr.splitlines() if line.startswith("cfknode fly:")]
    assert len(lines) == 1 and "the flight loop hung" in lines[0] and "log closed:" in lines[0], proc.stderr
    path, = logs.glob("*.mcap")
    log = read_log(path)
    assert not log.truncated  # closed: footer and summary written
    states = log.topic("/state")
    assert states and BLOCK_AT - 0.5 < states[-1]["t"] <= BLOCK_AT + 0.1  # recorded up to the hang, kept
    texts = [m["text"] for m in log.topic("/events")]
    assert any("the flight loop has not come back" in t for t in texts), texts
