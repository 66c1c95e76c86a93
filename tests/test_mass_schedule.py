"""``sim.mass_changes``: the plant reads its schedule through a cursor, not by scanning the list each step."""

from __future__ import annotations

import dataclasses
from typing import Iterator

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.sim_backend.crazyflie import SimCrazyflie
from cfknode.sim_backend.scenario import MassSchedule, mass_at
from cfknode.sim_backend.settings import MassChange


def test_the_schedule_gives_mass_at_for_every_time_forward_and_back():
    rng = np.random.default_rng(3)
    times = np.round(rng.uniform(0.0, 20.0, 300), 2)  # rounded: many equal times, listed-last wins
    changes = [MassChange(float(t), float(f)) for t, f in zip(times, rng.uniform(0.5, 1.5, 300))]
    changes += [MassChange(2.0, 1.3), MassChange(2.0, 0.7)]
    sched = MassSchedule(0.03, changes)
    forward = [k * 0.002 for k in range(12_000)]
    assert [sched.at(t) for t in forward] == [mass_at(t, 0.03, changes) for t in forward]
    back = rng.uniform(-1.0, 25.0, 500)  # out of order: the cursor steps back
    assert [sched.at(t) for t in back] == [mass_at(t, 0.03, changes) for t in back]
    assert MassSchedule(0.03, []).at(5.0) == 0.03


class CountingChanges(tuple):
    """A tuple that counts how often it is read whole."""

    reads = 0

    def __iter__(self) -> Iterator[MassChange]:
        type(self).reads += 1
        return super().__iter__()


def test_a_long_list_is_read_once_not_every_plant_step():
    cfg = load_config()
    changes = CountingChanges(MassChange(1.0 + 1e-3 * k, 1.0 + 0.1 * (k % 3)) for k in range(5000))
    sim = SimCrazyflie(cfg.vehicle, dataclasses.replace(cfg.sim, mass_changes=changes))
    reads = CountingChanges.reads
    sim.step_to(2.0)  # 1000 plant steps through 1000 of the changes
    assert CountingChanges.reads == reads
    assert sim._mass == pytest.approx(mass_at(2.0 - sim.dt, cfg.vehicle.mass, changes))
