"""The mass-step benches' shared report parts: wins without the oracle, ratio to the oracle, recovery text,
latency flags and the --cells subset."""

from __future__ import annotations

import argparse

import pytest

from cfknode.app.bench.hierarchical import CELLS, cell_overrides, parse_cells
from cfknode.app.bench.online import QUICK
from cfknode.app.bench.robustness import CELLS as ROBUST_CELLS, LAB, flight_overrides
from cfknode.app.bench.rows import (add_latency_arguments, add_plant_arguments, latency_flags, latency_note,
                                latency_overrides, oracle_ratios, plant_flags, plant_overrides, recovery_text,
                                summary_lines, wins)
from cfknode.app.cli import UsageError

CELL_MSE = [
    {"nominal": 0.03, "online": 0.01, "dob": 0.004, "oracle": 0.002},
    {"nominal": 0.05, "online": 0.02, "dob": 0.03, "oracle": 0.01},
]


def test_wins_leave_the_oracle_out_and_ratios_are_medians_over_cells() -> None:
    assert wins(CELL_MSE) == {"dob": 1, "online": 1}
    ratios = oracle_ratios(CELL_MSE, ("nominal", "online", "dob"))
    assert ratios["nominal"] == pytest.approx((15.0 + 5.0) / 2) and ratios["dob"] == pytest.approx((2.0 + 3.0) / 2)
    text = "\n".join(summary_lines(CELL_MSE, ("nominal", "online", "dob", "oracle")))
    assert "KNODE-MPC-Online 1 of 2" in text and "nominal MPC 0 of 2" in text and "nominal MPC 10.00" in text


def test_recovery_text_says_never_for_an_unrecovered_step() -> None:
    steps = [{"time_to_recover_s": 0.4211, "peak_error_m": 0.1}, {"time_to_recover_s": None, "peak_error_m": 0.3}]
    assert recovery_text(steps) == "0.42 / never" and recovery_text([]) == "-"


def test_latency_flags_reach_the_config_and_the_report() -> None:
    p = argparse.ArgumentParser()
    add_latency_arguments(p)
    fixed = p.parse_args([])
    assert latency_overrides(fixed) == {"online.latency": "fixed", "online.fixed_latency_s": 0.1}
    assert latency_flags(fixed) == " --latency fixed --fixed-latency 0.1" and "fixed 0.1 s" in latency_note(fixed)
    wall = p.parse_args(["--latency", "wall"])
    assert latency_flags(wall) == " --latency wall" and "wall" in latency_note(wall)


def test_the_benches_fly_the_ideal_plant_unless_told_aero_realistic() -> None:
    p = argparse.ArgumentParser()
    add_plant_arguments(p)
    default, real = p.parse_args([]), p.parse_args(["--aero", "realistic"])
    assert plant_overrides(default) == {"sim.aero": "ideal"} and plant_flags(default) == ""
    assert plant_overrides(real) == {"sim.aero": "realistic"} and plant_flags(real) == " --aero realistic"
    # Each bench's cell names the plant itself, so a change of the packaged default leaves its tables alone.
    assert cell_overrides(2.0, 0.8, 4.0, "/tmp", 0)["sim.aero"] == "ideal"
    assert QUICK.config("/tmp", 0)["sim.aero"] == "ideal"
    assert flight_overrides(ROBUST_CELLS[0], LAB, "mpc", "/tmp", 0)["sim.aero"] == "ideal"


def test_cells_subset() -> None:
    assert parse_cells(None) == CELLS
    assert parse_cells("2:0.8,4:1.2") == ((2.0, 0.8), (4.0, 1.2))
    with pytest.raises(UsageError, match="not one of the paper's cells"):
        parse_cells("5:0.8")
    with pytest.raises(UsageError, match="r:v pairs"):
        parse_cells("2")
