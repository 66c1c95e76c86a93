"""Deadlines on a wall clock: a flight's event loop waits on microsecond timers, and the slots a loop passes
over are counted as missed deadlines, live, in the log and in the summary (docs/design.md#honest-timing)."""

from __future__ import annotations

import asyncio
import selectors
from typing import Any

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.app.logs.reader import read_log
from cfknode.app.ui.summary import summary_from_log
from cfknode.kernel.clock import fine_timer_loop, run_loop
from cfknode.sim_backend.link_driver import lookup

PERIOD = 0.0025


def test_the_flights_event_loop_hands_the_kernel_a_sub_millisecond_wait(monkeypatch: pytest.MonkeyPatch) -> None:
    waits: list[float | None] = []
    real = selectors.SelectSelector._select  # type: ignore[attr-defined]

    def recording(self: Any, r: Any, w: Any, x: Any, timeout: float | None = None) -> Any:
        waits.append(timeout)
        return real(r, w, x, timeout)

    monkeypatch.setattr(selectors.SelectSelector, "_select", recording)

    async def nap() -> str:
        await asyncio.sleep(0.0503)
        return "woke"

    assert run_loop(nap()) == "woke"
    timed = [w for w in waits if w]
    # epoll would be handed 51 ms (whole milliseconds, rounded up); select gets the 50.3 ms itself, less what
    # passed before the wait.
    assert timed and 0.0 < max(timed) <= 0.0503
    loop = fine_timer_loop()
    try:
        assert isinstance(loop, asyncio.SelectorEventLoop)
    finally:
        loop.close()


class _Wall:
    """The simulator's clock, seen by the loop as a wall clock: its slots can pass while a tick works."""

    lockstep = False

    def __init__(self, inner: Any, late_wake: tuple[float, float] = (float("inf"), 0.0)) -> None:
        self._inner, self._late_wake = inner, late_wake  # (flight time, seconds): one sleep that ends late

    def now(self) -> float:
        return self._inner.now()

    async def sleep_until(self, t: float) -> None:
        if t >= self._late_wake[0]:
            t, self._late_wake = t + self._late_wake[1], (float("inf"), 0.0)
        await self._inner.sleep_until(t)


class _Overrun:
    """An observer whose bookkeeping takes some of the plant's time on chosen ticks: (flight time, seconds)."""

    def __init__(self, uri: str, at: tuple[tuple[float, float], ...]) -> None:
        self.uri, self.at, self.ticks_at = uri, list(at), []

    def on_tick(self, info: Any) -> None:
        if self.at and info.t >= self.at[0][0]:
            _, spent = self.at.pop(0)
            self.ticks_at.append(info.t)
            sim = lookup(self.uri).sim
            sim.step_to(sim.t + spent)


@pytest.mark.flight
def test_a_loop_that_runs_over_its_slot_records_the_slots_it_passed_over(tmp_path: Any,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    import cfknode.app.mission as mission

    cfg = load_config(overrides={
        "log.dir": str(tmp_path), "trajectory.kind": "hover", "trajectory.duration": 1.0,
        "trajectory.takeoff_duration": 1.0, "trajectory.settle_duration": 0.2, "trajectory.land_duration": 1.0})
    # Two ticks run 6 ms over (the next slot's whole window passes), one 3 ms (into the next slot, not past it),
    # and one tick wakes 3 ms late, in the slot after its own.
    overrun = _Overrun(cfg.radio.uri, ((1.0, 0.006), (1.5, 0.003), (2.0, 0.006)))
    parts_of = mission.FlightParts

    def with_wall_clock(**kw: Any) -> Any:
        return parts_of(**{**kw, "clock": _Wall(kw["clock"], (2.5, 0.003)),
                           "observers": [*kw.get("observers", []), overrun]})

    monkeypatch.setattr(mission, "FlightParts", with_wall_clock)
    res = mission.run_flight(cfg, name_hint="overrun")
    rec, s = res.record, res.summary
    assert len(overrun.ticks_at) == 3
    i = np.searchsorted(rec.t, overrun.ticks_at) + 1  # the tick after each overrun
    slots = np.floor((rec.t[i] - rec.t[i - 1]) / PERIOD + 1e-9)
    # Past a whole slot: that slot is passed over, and the tick after starts the slot it woke in, late.
    # Into the next slot only: that slot's tick starts at once, late but inside its deadline.
    assert list(rec.skipped[i]) == [1, 0, 1] and list(slots) == [2, 1, 2]
    assert all(rec.t[i] - rec.t[i - 1] > slots * PERIOD)  # each started after its slot began
    # The tick that woke in the next slot missed its deadline, and that slot counts as passed over: a slot
    # has one tick at most, so the next tick waits for its own slot.
    woke = int(np.searchsorted(rec.t, 2.5))
    assert rec.missed[woke] and rec.skipped[woke + 1] == 1
    assert np.floor(rec.t[woke + 1] / PERIOD + 1e-9) == np.floor(rec.t[woke] / PERIOD + 1e-9) + 1
    assert np.all(np.diff(np.floor(rec.t / PERIOD + 1e-9)) >= 1)
    assert s.skipped_slots == 3 and int(rec.skipped.sum()) == 3
    assert s.missed_deadlines == 3 + int(rec.missed.sum())
    # The log records them on the tick after, and a summary recomputed from it counts the same.
    ticks = read_log(s.log_path).topic("/tick")
    assert sum(m.get("skipped", 0) for m in ticks) == 3
    again = summary_from_log(read_log(s.log_path))
    assert (again.skipped_slots, again.missed_deadlines) == (3, s.missed_deadlines)
