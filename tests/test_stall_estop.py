"""``cfknode estop`` while the flight loop's thread is blocked, through the real cflib path (sim://).

The event loop that polls the e-stop mailbox is stuck with the loop; a watch thread polls in its
place and the supervisor passes a stop on to the radio at once, whose TX thread stops the
motors. Judged on the simulator's side, in simulated time (tests/test_loop_stall.py's Blocker).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cfknode.safety.estop_mailbox import find_flight, request
from test_loop_stall import FLYING, Blocker, _fly, _motors_off_at

pytestmark = [pytest.mark.flight, pytest.mark.process, pytest.mark.slow]


@dataclass
class EstopBlocker(Blocker):
    """Blocks the loop as Blocker does and, 0.3 s of simulated time into the block, sends one
    ``cfknode estop`` request from another thread; ``taken`` is whether the flight took it."""

    action: str = "stop"
    directory: Path = Path(".")
    taken: list[bool] = field(default_factory=list)
    t_request: float = float("nan")

    def _send_signals(self) -> None:
        while self.sim.t < self.t0 + 0.3:  # simulated time, whatever the machine's load
            time.sleep(0.005)
        self.t_request = self.sim.t
        flight = find_flight(self.directory)
        self.taken.append(request(flight, self.action, timeout=1.5))


def _blocked_flight(tmp_path: Path, action: str) -> tuple[Any, EstopBlocker]:
    blocker = EstopBlocker(uri="", signals=1, action=action, directory=tmp_path / "estop")
    # The stall alone would stop the motors only 1.9 s into the block.
    result, _ = _fly(tmp_path, blocker, **{"radio.stale_stop_s": 1.9, "safety.estop_dir": str(tmp_path / "estop")})
    assert blocker.state_at_block in FLYING, result.record.events
    return result, blocker


def test_an_estop_stop_reaches_the_motors_while_the_loop_is_blocked(tmp_path):
    result, blocker = _blocked_flight(tmp_path, "stop")
    assert blocker.taken == [True]  # acknowledged during the block (the loop was stuck for 4 s)
    t_off = _motors_off_at(blocker)
    assert blocker.t_request <= t_off < blocker.t0 + 1.0, (blocker.t0, blocker.t_request, t_off)
    assert all(s.motors == (0, 0, 0, 0) for s in blocker.samples if s.t >= t_off)
    assert result.outcome.cause == "estop_stop", result.outcome.message
    assert result.outcome.message.startswith("motors stopped: cfknode estop --robot ")


def test_an_estop_land_during_the_block_is_taken_and_the_radio_holds_descending(tmp_path):
    result, blocker = _blocked_flight(tmp_path, "land")
    assert blocker.taken == [True]
    t0 = blocker.t0
    at_block = next(s for s in blocker.samples if s.t >= t0)
    t_off = _motors_off_at(blocker)  # the stall's own stop, 1.9 s in: the land request did not stop them
    assert t_off > t0 + 1.5
    held = [s for s in blocker.samples if t0 + 0.2 <= s.t < t_off]
    assert held and all(s.setpoint.roll == 0.0 and s.setpoint.pitch == 0.0 for s in held)
    assert held[-1].p[2] < at_block.p[2] - 0.1 and np.linalg.norm(held[-1].p[:2] - at_block.p[:2]) < 0.2
    events = result.record.events
    assert any("cfknode estop --robot" in e and "--land" in e for e in events), events
