"""The unavoidable sag after a mass step through a thrust lag, and the robustness bench's height built on it."""

from __future__ import annotations

import math

import pytest

from cfknode.app.bench.robustness import (CELLS, CEILING, GROUND_Z, LAB, PAPER, PATTERN_HEIGHT, SAG_MARGIN, flight_overrides,
                                          markdown, unavoidable_sag)
from cfknode.app.bench.thrust_sag import G, lag_sag, step_sag
from cfknode.app.config import load_config


def _closed_form(c: float, h: float, tau: float) -> float:
    """The same fall solved by hand: v(t) = g[(c - 1)t - (c - h)tau(1 - e^-t/tau)] = 0, z at that t."""
    lo, hi = tau, 100.0 * tau  # v < 0 at tau, > 0 far out; bisect for the stop
    v = lambda t: (c - 1.0) * t - (c - h) * tau * (1.0 - math.exp(-t / tau))
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if v(mid) < 0.0 else (lo, mid)
    t = lo
    return -G * ((c - 1.0) * t * t / 2.0 - (c - h) * tau * (t - tau * (1.0 - math.exp(-t / tau))))


@pytest.mark.parametrize("tau", [0.015, 0.04, 0.08, 0.15])
def test_lag_sag_matches_the_closed_form(tau):
    assert lag_sag(1.05, 0.5 / 1.33, tau) == pytest.approx(_closed_form(1.05, 0.5 / 1.33, tau), rel=2e-3)


def test_the_hardest_cell_must_lose_most_of_a_metre():
    # T/W 1.05 at the clamp, thrust hovering the 0.5x vehicle when 1.33x arrives: ~0.85 m at 150 ms, ~tau^2.
    assert step_sag(1.05, 0.5, 1.33, 0.150) == pytest.approx(0.854, abs=0.005)
    assert step_sag(1.05, 0.5, 1.33, 0.015) == pytest.approx(0.0085, abs=0.0005)
    assert step_sag(1.10, 0.5, 1.33, 0.150) == pytest.approx(0.419, abs=0.005)
    # Reacting later only adds: 20 ms more is a quarter metre more at 150 ms.
    assert step_sag(1.05, 0.5, 1.33, 0.150, reaction_s=0.02) > step_sag(1.05, 0.5, 1.33, 0.150) + 0.2
    assert step_sag(1.05, 1.33, 0.5, 0.150) == 0.0  # lighter: nothing to fall
    with pytest.raises(ValueError):
        lag_sag(1.0, 0.5, 0.1)


def test_every_cell_flies_at_one_height_with_room_for_its_sag():
    worst = max(unavoidable_sag(c) for c in CELLS)
    assert worst == pytest.approx(0.854, abs=0.005)  # T/W 1.05 + 150 ms lag
    for pattern in (LAB, PAPER):
        assert pattern.height == PATTERN_HEIGHT
        assert pattern.height - GROUND_Z >= worst + SAG_MARGIN
        for cell in CELLS:
            cfg = load_config(overrides=flight_overrides(cell, pattern, "mpc+dob", "/tmp", 0))
            assert cfg.trajectory.height == PATTERN_HEIGHT
            # Inside the bench's fence and under a lab ceiling, with the fence margin above the pattern.
            assert cfg.safety.fence_max[2] == CEILING >= PATTERN_HEIGHT + cfg.safety.fence_margin
            # The climb keeps the lab circle's rate (2 s per metre), whatever the height.
            assert cfg.trajectory.takeoff_duration == pytest.approx(2.0 * PATTERN_HEIGHT)
    # The default config's own fence (2.0 m, 0.2 m margin) would fly the same pattern.
    default = load_config()
    assert PATTERN_HEIGHT <= default.safety.fence_max[2] - default.safety.fence_margin


def test_the_report_states_the_height():
    md = markdown([], ("mpc",), "cmd", "0", "full", (LAB, PAPER))
    assert f"r = 0.5 m at 0.4 m/s at {PATTERN_HEIGHT:g} m" in md and "no ground effect" in md
