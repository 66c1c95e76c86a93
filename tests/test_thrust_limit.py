"""Flying at the thrust limit and still tracking: the paper's cell r = 2 m at 0.8 m/s with its mass steps (0.5x,
then 1.33x) on a plant with thrust-to-weight 1.05 at the clamp after the second step, 100 ms of thrust lag, an
attitude loop reaching 0.83 of the command and body drag of 0.35 m/s^2 per m/s.

LONG: three full flights (the two with online learning start a trainer process).

The altitude must sag at the 1.33x step whatever a controller does: with the clamp commanded at the instant of
the step the thrust still follows through its lag (``thrust_sag.step_sag``: 0.38 m at 100 ms, 0.56 m with 20 ms
of detection and command path). The bounds are therefore horizontal error under 0.3 m and a sag within that
physical bound; a plan at the top of the thrust cone used to leave the horizontal no room (1.08 m of error).
The paper's method (no fast layer, online learning) reached the ground here until the fall guard
(flight/fall_guard.py) flew the clamp at the step: it must not fall.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cfknode.app.bench.hierarchical import cell_overrides
from cfknode.app.bench.mass_steps import SECOND_FACTOR, mass_schedule
from cfknode.app.bench.thrust_sag import step_sag
from cfknode.app.config import load_config
from cfknode.app.mission import run_flight
from cfknode.sim_backend.plant import thrust_scale_for_thrust_to_weight

DURATION = 8.0  # s of pattern: the paper's steps at 2 s and 5 s into it
TAU = 0.1  # s, the plant's thrust lag
GROUND_Z = 0.05
CONTROLLERS: dict[str, dict[str, Any]] = {
    "mpc+dob": {"controller.adaptation": "dob"},  # the default controller
    "online+dob": {"controller.adaptation": "dob", "online.enabled": True},
    "paper": {"controller.adaptation": "none", "online.enabled": True},  # KNODE-MPC-Online as the paper flies it
}
# A fixed delay from a window's end to its model flying: the same flight on a loaded machine.
FIXED_LATENCY = {"online.latency": "fixed", "online.fixed_latency_s": 0.1}


def overrides(label: str, log_dir: str) -> dict[str, Any]:
    base = {**cell_overrides(2.0, 0.8, DURATION, log_dir, 0), "dashboard.enabled": False}
    vehicle = load_config(overrides=base).vehicle
    return {**base, "sim.mass_changes": list(mass_schedule(base).both), "sim.motor_time_constant": TAU,
            "sim.thrust_map_scale": thrust_scale_for_thrust_to_weight(1.05, vehicle, SECOND_FACTOR),
            "sim.attitude_gain": 0.83, "sim.drag": [0.0135, 0.0135, 0.0], **FIXED_LATENCY, **CONTROLLERS[label]}


@dataclass(frozen=True)
class Result:
    peak_xy: float  # m, largest horizontal error during the pattern
    peak_z: float  # m, largest altitude error during the pattern
    ground: bool
    outcome: str


def fly(label: str, log_dir: Path) -> Result:
    res = run_flight(load_config(overrides=overrides(label, str(log_dir))), name_hint=label.replace("+", "-"))
    t0, t1 = res.summary.window
    pattern = (res.record.t >= t0) & (res.record.t <= t1)
    err = res.record.p[pattern] - res.record.p_ref[pattern]
    return Result(float(np.linalg.norm(err[:, :2], axis=1).max()), float(np.abs(err[:, 2]).max()),
                  bool(np.any(res.record.p[pattern, 2] < GROUND_Z)), res.outcome.message)


@pytest.fixture(scope="module")
def flights(tmp_path_factory) -> dict[str, Result]:
    return {label: fly(label, tmp_path_factory.mktemp(label.replace("+", "-"))) for label in CONTROLLERS}


def test_no_controller_falls(flights: dict[str, Result]) -> None:
    for label, r in flights.items():
        assert not r.ground, (label, r)
        assert r.outcome.startswith("flight complete"), (label, r)


@pytest.mark.parametrize("label", ["mpc+dob", "online+dob"])
def test_the_layer_tracks_at_the_thrust_limit(flights: dict[str, Result], label: str) -> None:
    r = flights[label]
    assert r.peak_xy < 0.3, r
    # No more than the fall the lag forces with 20 ms to react (0.56 m; 0.50 m flown).
    assert r.peak_z < step_sag(1.05, 0.5, SECOND_FACTOR, TAU, reaction_s=0.02), r


def test_the_paper_s_method_stops_its_fall_within_the_lag_s_bound(flights: dict[str, Result]) -> None:
    # Without a fast layer the fall guard flies the clamp 10 ms after the step; nominal MPC holds 1.33x 0.34 m
    # low without integral action, so the altitude's bound is the sag with 20 ms to react (0.56 m; 0.45 m flown).
    r = flights["paper"]
    assert r.peak_xy < 0.3, r
    assert r.peak_z < step_sag(1.05, 0.5, SECOND_FACTOR, TAU, reaction_s=0.02), r
