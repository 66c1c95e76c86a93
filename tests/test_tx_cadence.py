"""The radio's no-burst send schedule."""

from __future__ import annotations

from cfknode.app.backends.tx_cadence import Cadence


def test_due_on_the_grid_and_first_call_starts_it() -> None:
    c = Cadence(0.01)
    period = 0.0025  # 400 Hz ticks against a 100 Hz schedule
    due = [k for k in range(40) if c.due(k * period)]
    assert due == list(range(0, 40, 4))


def test_falling_behind_restarts_the_grid_without_a_burst() -> None:
    c = Cadence(0.01, next_t=0.0)
    assert c.due(0.0)
    assert c.due(0.5)  # 49 slots missed: one packet, not 49
    assert not c.due(0.505)
    assert c.due(0.51)


def test_never_due_from_infinity() -> None:
    c = Cadence(0.05, next_t=float("inf"))
    assert not any(c.due(t) for t in (0.0, 1.0, 1e9))
