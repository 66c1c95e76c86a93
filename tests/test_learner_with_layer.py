"""The learner and the fast layer together against either alone, on one short mass-step flight.

Three lockstep flights through ``run_flight`` on the same plant and seed: MPC with the fast layer
(``controller.adaptation: dob``), KNODE-MPC-Online without it, and KNODE-MPC-Online with it. The
plant is the robustness bench's mass cell on its lab circle as the bench flew it in docs/results.md
(r = 0.5 m at 0.4 m/s, 6 s of pattern, mass 0.5x at 1.5 s and 1.33x at 3.75 s into it).

Measured on this flight with the fixed 0.1 s model latency (MSE in m^2):

| seed | mpc+dob | online | online+dob |
|---|---|---|---|
| 0 | 3.58e-4 | 1.06e-2 | 3.04e-4 |
| 1 | 4.05e-4 | 1.03e-2 | 4.24e-4 |
| 2 | 3.40e-4 | 6.73e-3 | 6.69e-4 |
| 3 | 3.38e-4 | 9.82e-3 | 8.96e-4 |
| 4 | 3.54e-4 | 7.33e-3 | 4.00e-4 |

The layer under the learner wins over the learner alone on every seed, by 10-35x: the learner
alone needs a window, a training round and the gate after each step, the layer sees a step in
~40 ms. The learner on top of the layer does not reliably win over the layer alone (1.18x better
on seed 0, 1.05-2.7x worse on seeds 1-4): after a mass step the layer already holds the whole
error, and the learner's models seem to add more noise than they remove. Nor does it where the
learner alone is the better one: with linear drag (0.05 N/(m/s) in x, y) on a 0.3 m circle at
1 m/s the learner alone flew 7.9e-4 and 8.3e-4 (seeds 0, 1), the layer 2.4e-3 twice, and the two
together 2.4e-3 and 2.3e-3. That half of the acceptance claim is recorded as an expected failure on
seed 2, strict, so the suite says so the day it holds.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cfknode.app.bench.robustness import GROUND_Z, LAB, Cell, flight_overrides
from cfknode.app.config import load_config
from cfknode.app.mission import run_flight

SEED = 2
MASS_STEPS = Cell("mass 0.5x then 1.33x", mass_steps=True)
PATTERN = replace(LAB, duration=6.0)

# Every key that picks the controller is set for every flight: the defaults may move.
CONTROLLERS: dict[str, dict[str, Any]] = {
    "mpc+dob": {"controller.kind": "mpc", "online.enabled": False, "controller.adaptation": "dob"},
    "online": {"controller.kind": "mpc", "online.enabled": True, "controller.adaptation": "none"},
    "online+dob": {"controller.kind": "mpc", "online.enabled": True, "controller.adaptation": "dob"},
}
# A fixed delay from a window's end to its model flying: the same flight on a loaded machine.
FIXED_LATENCY = {"online.latency": "fixed", "online.fixed_latency_s": 0.1}


@dataclass(frozen=True)
class Result:
    mse: float
    ground: bool  # below GROUND_Z during the pattern
    outcome: str


def fly(label: str, log_dir: Path) -> Result:
    overrides = {**flight_overrides(MASS_STEPS, PATTERN, "mpc", str(log_dir), SEED), **FIXED_LATENCY,
                 **CONTROLLERS[label]}
    res = run_flight(load_config(overrides=overrides), name_hint=label.replace("+", "-"))
    t0, t1 = res.summary.window
    pattern = (res.record.t >= t0) & (res.record.t <= t1)
    ground = bool(np.any(res.record.p[pattern, 2] < GROUND_Z)) if pattern.any() else True
    return Result(float(res.summary.mse), ground, res.outcome.message)


@pytest.fixture(scope="module")
def flights(tmp_path_factory) -> dict[str, Result]:
    return {label: fly(label, tmp_path_factory.mktemp(label.replace("+", "-"))) for label in CONTROLLERS}


def test_every_flight_stays_up_and_completes(flights: dict[str, Result]) -> None:
    for label, r in flights.items():
        assert not r.ground, (label, r)
        assert r.outcome.startswith("flight complete"), (label, r)
        assert np.isfinite(r.mse), (label, r)


def test_the_layer_under_the_learner_beats_the_learner_alone(flights: dict[str, Result]) -> None:
    # 10-35x on seeds 0-4 (10x on this one): 4x is far from a hair and far from the measured worst.
    assert flights["online+dob"].mse < flights["online"].mse / 4.0, flights


@pytest.mark.xfail(strict=True, reason="not met: online+dob is 1.18x better than mpc+dob on seed 0 of this "
                                       "flight, 1.05-2.7x worse on seeds 1-4 (seed 2 flown here)")
def test_the_learner_on_the_layer_beats_the_layer_alone(flights: dict[str, Result]) -> None:
    assert flights["online+dob"].mse < flights["mpc+dob"].mse / 1.1, flights
