"""`cfknode bench robustness`: verdicts, recovery time, the report, and a short run of the whole stack."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from cfknode.app.bench.robustness import CELLS, CONTROLLERS, LAB, RunResult, flight_overrides, markdown, recovery_time, wins
from cfknode.app.cli import main
from cfknode.app.config import load_config
from cfknode.sim_backend.plant import thrust_to_weight


def _run(cell, ctrl, mse, **flags):
    return RunResult(cell, "lab", ctrl, mse, flags.get("ground", False), flags.get("diverged", False),
                     flags.get("tripped", False), "flight complete: landed", None, 1.0)


def test_recovery_time_is_when_the_error_settles_back():
    t = np.arange(0.0, 6.0, 0.01)
    err = np.full_like(t, 0.01)
    err[(t >= 2.0) & (t < 2.7)] = 0.2  # a 0.7 s excursion after a step at 2 s
    assert recovery_time(t, err, 2.0, 6.0) == pytest.approx(0.69, abs=0.011)
    err[t >= 2.0] = 0.2  # never back
    assert math.isinf(recovery_time(t, err, 2.0, 6.0))


def test_thrust_to_weight_cells_set_the_thrust_map():
    cell = next(c for c in CELLS if c.name == "T/W 1.05 + 150 ms lag")
    ov = flight_overrides(cell, LAB, "mpc+dob", "/tmp", 0)
    cfg = load_config(overrides=ov)
    assert thrust_to_weight(cfg.vehicle, cfg.sim.thrust_map_scale, 1.33) == pytest.approx(1.05)
    assert cfg.sim.motor_time_constant == 0.15 and cfg.controller.adaptation == "dob"
    assert [c.factor for c in cfg.sim.mass_changes] == [0.5, 1.33]


def test_markdown_flags_failures_and_counts_wins():
    results = [_run("a", "mpc", 0.02), _run("a", "mpc+dob", 0.01), _run("b", "mpc", 0.03),
               _run("b", "mpc+dob", 0.001, ground=True, tripped=True)]
    assert wins(results, ("mpc", "mpc+dob")) == {"mpc": 1, "mpc+dob": 1}
    md = markdown(results, ("mpc", "mpc+dob"), "cmd", "0", "quick", (LAB,))
    assert "**0.01**" in md and "0.001 GS" in md and "FAILED" in md and "mpc+dob on b / lab (GS)" in md
    assert "| mpc | 0.03 | b / lab | none | 1 of 2 | 1 of 2 |" in md


def test_near_ties_count_for_every_controller_within_the_margin():
    results = [_run("a", "mpc", 0.0100), _run("a", "mpc+dob", 0.0101), _run("a", "online+dob", 0.0103),
               _run("b", "mpc", 0.02), _run("b", "online+dob", 0.01), _run("b", "oracle", 0.001)]
    controllers = ("mpc", "mpc+dob", "online+dob", "oracle")
    assert wins(results, controllers) == {"mpc": 1, "mpc+dob": 0, "online+dob": 1, "oracle": 0}
    # 1 % over the lowest is a near tie at 2 %, 3 % is not; the oracle is a reference, never counted.
    assert wins(results, controllers, 0.02) == {"mpc": 1, "mpc+dob": 1, "online+dob": 1, "oracle": 0}


def test_an_exact_tie_is_the_lowest_for_each_and_bold_for_each():
    # The learner kept no model: online+dob flew as mpc+dob, to the last digit.
    results = [_run("a", "mpc", 0.02), _run("a", "mpc+dob", 0.01), _run("a", "online+dob", 0.01)]
    controllers = ("mpc", "mpc+dob", "online+dob")
    assert wins(results, controllers) == {"mpc": 0, "mpc+dob": 1, "online+dob": 1}
    md = markdown(results, controllers, "cmd", "0", "quick", (LAB,))
    assert "| a | lab | 0.02 | **0.01** | **0.01** |" in md


def test_short_robustness_bench_runs_the_whole_stack(tmp_path):
    assert set(CONTROLLERS) >= {"geometric", "mpc", "mpc+dob", "online", "online+dob"}
    args = ["bench", "robustness", "--cells", "mocap latency 25 ms,motor lag 80 ms", "--controllers", "mpc,mpc+dob",
            "--patterns", "lab", "--duration", "2", "--jobs", "1", "--out", str(tmp_path)]
    assert main(args) == 0
    data = json.loads((tmp_path / "robustness.json").read_text())
    assert data["command"].startswith("cfknode bench robustness") and data["mode"] == "full"
    assert len(data["runs"]) == 4
    for run in data["runs"]:
        assert 0.0 <= run["mse"] < 0.01, run
        assert not (run["ground"] or run["diverged"] or run["tripped"]), run
    assert "| mocap latency 25 ms | lab |" in (tmp_path / "robustness.md").read_text()


def test_bad_arguments_are_usage_errors(tmp_path):
    assert main(["bench", "robustness", "--controllers", "nope", "--out", str(tmp_path)]) == 2
