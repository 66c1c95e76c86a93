"""The learner and the fast layer together against either alone, on one short flight with drag and mass steps.

Three lockstep flights through ``run_flight`` on the same plant and seed: MPC with the fast layer
(``controller.adaptation: dob``), KNODE-MPC-Online without it, and KNODE-MPC-Online with it. The
plant is the robustness bench's mass cell on its lab circle as the bench flew it in docs/results.md
(r = 0.5 m at 0.4 m/s, 6 s of pattern, mass 0.5x at 1.5 s and 1.33x at 3.75 s into it), with linear
drag 0.05 N/(m/s) in x and y: the steps need the layer, the drag is a state-dependent residual.

Measured on this flight with the fixed 0.1 s model latency (MSE in m^2; the layer with the
accelerometer and the mass fitted at a step, its offset behind a second pole, acting on an axis once
the error there is real; the estimator predicting with the flown acceleration; at 1.5 m as the
robustness bench flies):

| seed | mpc+dob | online | online+dob | online+dob / mpc+dob |
|---|---|---|---|---|
| 0 | 5.98e-4 | 5.76e-3 | 5.80e-4 | 0.97 |
| 1 | 5.93e-4 | 6.36e-3 | 5.84e-4 | 0.99 |
| 2 | 6.03e-4 | 5.83e-3 | 5.88e-4 | 0.98 |

The layer under the learner beats the learner alone on every seed by 9.9-10.9x: the learner alone needs
a window, a training round and the gate after each step, the layer knows a step within a sample.
The learner on top of the layer beats the layer alone by 1.4-2.9 % on every seed (1.00, 1.00 and
0.98 before the gate's floor, ``online.gate_layer_min_gain``, which turns away candidates fitted
to noise):
the learner's targets are the acceleration not explained by the command as the layer shaped it
(thrust from the estimated mass), so the mass stays with the layer, and at each swap the layer's
offset is re-based by what the new model explains. Its gain is small because online training's
strong weight decay keeps each round's net close to a constant (on the circle below the flying
model held 5-15 % of the drag), and because beside the layer the gate wants a candidate 2 % better
without constants over five consecutive fresh samples (``online.gate_layer_margin``,
``online.gate_layer_steps``; over a single step at 5 % it was 0.99 / 1.00 / 0.98 here, and lost 5-15 %
on the robustness bench's quiet cells). The test flies seed 2.

Not this flight: with the same drag on a 0.3 m circle at 1 m/s the layer alone (3.6e-3) is worse
than the MPC alone (7.4e-4), and so is online+dob (4.0e-3), while the learner alone (8.2e-4) matches
the MPC. That circle is unstable for the nominal MPC without drag (5.2e-2, the error grows through
the pattern); the drag's damping holds it, and the layer, estimating the drag correctly, cancels it
(a faster xy observer is worse: 1.1e-2 at 4 Hz). It is no contest between learner and layer.
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
DRAG = 0.05  # N/(m/s), x and y
DRAG_AND_STEPS = Cell("drag, mass 0.5x then 1.33x", (("sim.drag", [DRAG, DRAG, 0.0]),), mass_steps=True)
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
    overrides = {**flight_overrides(DRAG_AND_STEPS, PATTERN, "mpc", str(log_dir), SEED), **FIXED_LATENCY,
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
    # 9.7-10.8x on seeds 0-2 (10x on this one): 4x is far from a hair and far from the measured worst.
    assert flights["online+dob"].mse < flights["online"].mse / 4.0, flights


def test_the_learner_on_the_layer_beats_the_layer_alone(flights: dict[str, Result]) -> None:
    # 0.98 on this seed (0.97 and 0.99 on seeds 0 and 1): a 1 % lead is what the closest seed holds.
    assert flights["online+dob"].mse < flights["mpc+dob"].mse / 1.01, flights
