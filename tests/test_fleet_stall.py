"""A stalled wall-clock fleet holds a stack in order: two sim:// robots stacked in one column, flown
through the real cflib path on one wall clock (``cfknode fly --robots``), their shared loop thread
blocked mid-pattern. Each radio's TX thread holds on its own (backends/stale_setpoint.py): the drone
with another below it holds level at its hover thrust, the lowest one descends, so the stack's gap
opens instead of closing. What the vehicles did is read on the simulator's side, after every plant
step, stamped with simulated time; nothing here asserts a wall-clock duration."""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from cfknode.app.fleet.robots import run_robot_fleet
from cfknode.kernel.setpoint import thrust_command
from cfknode.sim_backend.link_driver import lookup
from test_fleet_robots import cfg_for, write_robots

pytestmark = [pytest.mark.flight, pytest.mark.process, pytest.mark.slow]  # as tests/speeds.py gives them

_uris = itertools.count(9800, 2)  # even: the two robots share one simulated radio
BLOCK_AT = 2.0  # s of flight time: mid-pattern, cf2 right above cf1
BLOCK_S = 0.9  # wall: past the hold (4 TX slots), short of the stop (radio.stale_stop_s 1.9 here)
HELD = (0.2, 0.6)  # s after the block began (simulated): both radios hold by then, and still do
# ... and before it ended: each simulator steps to the wall clock from its own thread, and on a loaded host it can
# lag the wall by a few tenths of a second, so the loop's first setpoints after the block can land inside HELD.


@dataclass
class _Stall:
    """The fleet's dashboard hook (``run_robot_fleet(dashboard=...)``): a tick observer on cf1 blocks
    the loops' one thread once at ``BLOCK_AT``, and every plant step of both vehicles is recorded."""

    uris: list[str]
    t0: float = float("nan")  # simulated time when the block began
    t0s: list[float] = field(default_factory=list)  # each simulator's time when the block began ...
    t1s: list[float] = field(default_factory=list)  # ... and when it ended, before the loops sent anything again
    blind: list[int] = field(default_factory=lambda: [0, 0])  # each supervisor's blind (descending) thrust
    hover: list[int] = field(default_factory=lambda: [0, 0])  # each drone's hover thrust, as its flight stack believes
    samples: list[list[tuple[float, float, Any]]] = field(default_factory=lambda: [[], []])
    _sims: list[Any] = field(default_factory=list)

    def observers(self, i, drone, reference, controller, supervisor, coordinator):
        self.blind[i] = int(supervisor.blind_setpoint.thrust)
        vehicle = drone.config.vehicle  # the robots file's type: the flight stack's belief
        self.hover[i] = thrust_command(vehicle.mass * vehicle.gravity, vehicle)
        stall = self

        class _Tap:
            def on_tick(self, info):
                if not stall._sims:
                    stall._sims = [lookup(u).sim for u in stall.uris]
                    for k, sim in enumerate(stall._sims):
                        sim.add_step_observer(lambda t, s, k=k, sim=sim: stall.samples[k].append(
                            (t, float(s[2]), sim.firmware.active_setpoint)))
                if i == 0 and info.t >= BLOCK_AT and np.isnan(stall.t0):
                    stall.t0s = [sim.t for sim in stall._sims]
                    stall.t0 = stall.t0s[0]
                    time.sleep(BLOCK_S)  # the loops' one thread is stuck here: no drone's loop runs
                    stall.t1s = [sim.t for sim in stall._sims]

        return [_Tap()]


def test_a_stalled_stack_holds_the_upper_drone_level_and_lets_the_lowest_descend(tmp_path):
    base = next(_uris)
    path = write_robots(tmp_path / "lab.yaml", {"cf1": (f"sim://{base}", (0.5, 0.0, 0.0), True),
                                                "cf2": (f"sim://{base + 1}", (0.5, 0.5, 0.0), True)})
    cfg = cfg_for(tmp_path, path, **{"fleet.layout": "stack", "fleet.stack_spacing": 0.6, "trajectory.duration": 3.0,
                                     "radio.stale_stop_s": 1.9})
    stall = _Stall([f"sim://{base}", f"sim://{base + 1}"])
    result = run_robot_fleet(cfg, ["cf1", "cf2"], name_hint="stall-stack", dashboard=stall)
    t0 = stall.t0
    assert not np.isnan(t0), [d.outcome.message for d in result.drones]
    at_block = [next(s for s in samples if s[0] >= a) for samples, a in zip(stall.samples, stall.t0s)]
    assert at_block[1][1] - at_block[0][1] > 0.4, at_block  # cf2 right above cf1 when the loop stopped
    held = [[s for s in samples if a + HELD[0] <= s[0] <= a + HELD[1] and s[0] < b]
            for samples, a, b in zip(stall.samples, stall.t0s, stall.t1s)]
    assert all(len(h) > 50 for h in held)  # recorded every plant step
    for k, h in enumerate(held):
        for _, _, sp in h:
            assert (sp.roll, sp.pitch, sp.yaw_rate) == (0.0, 0.0, 0.0) and sp.thrust > 0, (k, sp)  # a level hold
    # cf1, the lowest: the descending hold (its blind thrust, a little under hover). cf2, above it: level,
    # at its hover thrust (never more than it last asked for). Before, both descended alike.
    assert all(sp.thrust <= stall.blind[0] for _, _, sp in held[0])
    # "Last asked for": the radio's last fresh command, one of cf2's commands around the block (which tick was
    # the last to go out before the thread stopped is the wall clock's, not the test's).
    a = stall.t0s[1]
    asked = {sp.thrust for t, _, sp in stall.samples[1]
             if a - 0.1 <= t <= a + HELD[0] and (sp.roll, sp.pitch) != (0.0, 0.0)}
    hover = stall.hover[1]
    holds = {sp.thrust for _, _, sp in held[1]}
    assert len(holds) == 1 and holds.pop() in {min(c, hover) for c in asked} and all(
        sp.thrust > stall.blind[1] for _, _, sp in held[1]), (sorted(asked), hover, stall.blind, held[1][0])
    # So the stack's gap opens: the lower drone sinks faster than the upper one.
    sink = [h[0][1] - h[-1][1] for h in held]
    assert sink[0] > sink[1] + 0.01, sink
    assert held[1][-1][1] - held[0][-1][1] >= at_block[1][1] - at_block[0][1], (held[0][-1], held[1][-1])
