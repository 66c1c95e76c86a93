"""The estimator's flown acceleration in closed loop: two short lockstep flights of the plain MPC on the
robustness bench's nominal plant and lab circle, the estimator predicting with the command as if it acted at
once (``estimator.attitude_lag: 0``) and through the attitude loop's lag (the default). On this 3 s pattern
(MSE in m^2) 3.04e-5 against 1.87e-5; with 6 s of pattern 1.055e-5 against 6.50e-6
(docs/history.md#the-estimators-input)."""

from __future__ import annotations

from dataclasses import replace

from cfknode.app.bench.robustness import CELLS, LAB, flight_overrides
from cfknode.app.config import load_config
from cfknode.app.mission import run_flight

NOMINAL = next(c for c in CELLS if c.name == "motor lag 15 ms")  # the simulator's own motor: nothing differs
PATTERN = replace(LAB, duration=3.0)


def fly_mse(tmp_path, lag: float | None) -> float:
    overrides = flight_overrides(NOMINAL, PATTERN, "mpc", str(tmp_path), 0)
    if lag is not None:
        overrides["estimator.attitude_lag"] = lag
    res = run_flight(load_config(overrides=overrides), name_hint="estimator")
    assert res.outcome.message.startswith("flight complete"), res.outcome
    return float(res.summary.mse)


def test_the_flown_acceleration_tracks_better_than_the_command(tmp_path) -> None:
    assert load_config().estimator.attitude_lag > 0.0  # the default predicts with the flown acceleration
    at_once = fly_mse(tmp_path / "at_once", 0.0)
    flown = fly_mse(tmp_path / "flown", None)
    assert flown < 0.8 * at_once, (flown, at_once)
