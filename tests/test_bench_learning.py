"""``cfknode bench learning``: its cells (trajectories, placements, refusals, per-pass windows) and one quick
run through the real path."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest

from cfknode.app.bench.learning import (Job, Run, cell_refusal, flight_overrides, markdown, ratio, run_job,
                                        select_cells)
from cfknode.app.bench.learning_cells import (CELLS, CONTROLLERS, FLEET_ONLY, LearnCell, QUICK_CELLS,
                                              SURFACE_MIN_HEIGHT, ground_threshold, pass_errors, refusal)
from cfknode.app.config import load_config
from cfknode.flight.trajectory import make_trajectory

CFG = load_config()
BY_NAME = {c.name: c for c in CELLS}


def _refusal(cell: LearnCell) -> str | None:
    return refusal(cell, CFG.vehicle, CFG.controller.min_thrust_fraction, CFG.controller.max_thrust_fraction)


def _args(**kw) -> argparse.Namespace:
    base = dict(quick=False, seeds=3, groups="", cells="", duration=0.0)
    return argparse.Namespace(**{**base, **kw})


def test_every_cell_loads_flies_the_realistic_plant_and_its_pattern():
    for cell in (c for c in CELLS if cell_refusal(c) is None):
        for controller in CONTROLLERS:
            cfg = load_config(overrides=flight_overrides(Job(cell, controller, 1, "/tmp", 6.0)))
            assert cfg.sim.aero == "realistic" and cfg.sim.seed == 1 and cfg.online.latency == "fixed"
            assert cfg.trajectory.kind == cell.kind and cfg.trajectory.duration == 6.0
            assert cfg.online.enabled == (controller.startswith("online"))
        ref = make_trajectory(cfg.trajectory, cfg.sim.initial_position)
        t0, t1 = ref.pattern_window
        p = ref.sample(np.arange(t0, t1, 0.01)).p
        inside = (p >= np.array(cfg.safety.fence_min)) & (p <= np.array(cfg.safety.fence_max))
        assert inside.all(), cell.name


def test_layer_rows_fly_the_configured_layer_and_the_others_none():
    assert "controller.adaptation" not in CONTROLLERS["layer"] and "controller.adaptation" not in CONTROLLERS["online+layer"]
    assert CONTROLLERS["nominal"]["controller.adaptation"] == CONTROLLERS["online"]["controller.adaptation"] == "none"
    # A --set on the command line reaches every flight, after the rows: the layer rows fly it.
    job = Job(BY_NAME["circle r=0.5 v=1"], "layer", 0, "/tmp", 4.0, (("controller.adaptation", "l1"),))
    assert load_config(overrides=flight_overrides(job)).controller.adaptation == "l1"


def test_what_the_crazyflie_cannot_fly_is_refused_with_the_reason():
    fast = BY_NAME["circle r=0.3 v=2"]
    assert fast.peak_acceleration == pytest.approx(4.0 / 0.3)
    assert "clamp" in _refusal(fast)
    assert "up" in _refusal(BY_NAME["vertical A=0.3 f=1"])
    # Past the reserve the pre-flight check keeps, though under the clamp: refused by the flights' own check.
    assert _refusal(BY_NAME["vertical A=0.5 f=0.5"]) is None
    assert "needs 14.74 m/s^2 of thrust" in cell_refusal(BY_NAME["vertical A=0.5 f=0.5"])
    for name in ("circle r=0.3 v=1", "circle r=0.3 v=1.5", "circle r=0.5 v=2", "vertical A=0.4 f=0.5",
                 "surface h=6 cm v=1", "stacked pair dz=0.5 r=0.5 v=0.4"):
        assert cell_refusal(BY_NAME[name]) is None, name


def test_fast_loops_get_the_tilt_they_need_plus_a_margin():
    cfg = load_config(overrides=BY_NAME["circle r=0.5 v=2"].config("layer", 0, "/tmp"))
    need = math.degrees(math.atan2(8.0, 9.81))  # v^2/r = 8 m/s^2
    assert need + 5.0 < cfg.controller.max_tilt_deg < cfg.safety.max_tilt_deg
    assert load_config(overrides=BY_NAME["circle r=0.3 v=1"].config("layer", 0, "/tmp")).controller.max_tilt_deg == 30.0


def test_vertical_cells_climb_at_their_peak_rate_and_frequency():
    cell = BY_NAME["vertical A=0.4 f=0.5"]
    cfg = load_config(overrides=cell.config("layer", 0, "/tmp"))
    ref = make_trajectory(cfg.trajectory, cfg.sim.initial_position)
    t0, t1 = ref.pattern_window
    s = ref.sample(np.arange(t0, t1, 1e-3))
    assert np.max(s.v[:, 2]) == pytest.approx(2.0 * math.pi * 0.5 * 0.4, rel=1e-3)  # the climb rate the inflow sees
    assert np.ptp(s.p[:, 2]) == pytest.approx(0.8, abs=1e-3) and np.allclose(s.v[:, :2], 0.0)
    assert cell.frequency_hz == pytest.approx(0.5)


def test_surface_transit_flies_in_ground_effect_with_the_training_floor_under_it():
    for cell in (c for c in CELLS if c.group == "surface"):
        cfg = load_config(overrides=cell.config("online+layer", 0, "/tmp"))
        ref = make_trajectory(cfg.trajectory, cfg.sim.initial_position)
        t0, t1 = ref.pattern_window
        z = ref.sample(np.arange(t0, t1, 0.01)).p[:, 2]
        assert 0.04 <= z.min() and z.max() <= 0.08  # 4-8 cm over the floor for the whole pattern
        assert cfg.online.min_height == SURFACE_MIN_HEIGHT < z.min()  # windows are recorded there
        assert cfg.safety.fence_min[2] < 0.0  # the fence's floor is under the ground
        assert ground_threshold(cell) < z.min()  # a fall is lower than the transit


def test_the_stacked_pair_is_a_stack_fleet_of_two():
    cfg = load_config(overrides=BY_NAME["stacked pair dz=0.5 r=0.5 v=0.4"].config("online", 0, "/tmp"))
    assert cfg.fleet.size == 2 and cfg.fleet.layout == "stack" and cfg.fleet.stack_spacing == 0.5
    assert cfg.safety.fence_max[2] > cfg.trajectory.height + 0.5  # the upper drone inside the fence
    assert cfg.fleet.neighbour_input  # the lower drone's model sees where the upper one is


def test_pass_errors_average_each_window_around_its_pass():
    t = np.arange(0.0, 10.0, 0.01)
    err2 = np.where(np.abs(t - 2.0) <= 0.35, 4.0, 1.0)  # 4 over the first pass's window (and a little more), else 1
    out = pass_errors(t, err2, np.array([2.0, 6.0, 20.0]), half=0.3)
    assert out[0] == pytest.approx(4.0) and out[1] == pytest.approx(1.0) and math.isnan(out[2])


def test_cells_are_selected_by_group_name_and_quick():
    assert {c.group for c in select_cells(_args(groups="loops"))} == {"loops"}
    assert [c.name for c in select_cells(_args(quick=True))] == list(QUICK_CELLS)
    assert [c.name for c in select_cells(_args(cells="vertical A=0.4 f=0.5"))] == ["vertical A=0.4 f=0.5"]
    from cfknode.app.errors import UsageError

    with pytest.raises(UsageError):
        select_cells(_args(groups="nope"))


def test_the_table_has_a_row_per_controller_and_ratios_seed_by_seed():
    cell = BY_NAME["circle r=0.5 v=1"]
    runs = [Run(cell.name, c, s, mse * (1 + s), 0.0, 0.01, False, False, "flight complete: landed", 0, 0, 1.0)
            for s in (0, 1) for c, mse in (("nominal", 4.0), ("layer", 2.0), ("online+layer", 1.0), ("online", 3.0))]
    assert ratio(runs, cell.name, "online+layer", "layer") == pytest.approx(0.5)
    assert ratio(runs, cell.name, "online+layer", "nominal") == pytest.approx(0.25)
    md = markdown([cell], ["x: refused"], runs, tuple(CONTROLLERS), "cfknode bench learning", "0.1.0", "full", "dob")
    assert "`cfknode bench learning`, cfknode 0.1.0, mode full" in md and "Refused" in md
    rows = [line for line in md.splitlines() if line.startswith("| ") and "MPC" in line]
    assert len(rows) == 4
    assert "| circle r=0.5 v=1 | 0.50 | 0.25 | 0.75 | - |" in md  # no ceiling row flown: its ratio is "-"


@pytest.mark.slow
def test_quick_bench_flies_every_row_through_the_real_path(tmp_path, capsys):
    from cfknode.app.cli import main

    code = main(["bench", "learning", "--quick", "--jobs", "1", "--duration", "2", "--json", "--out", str(tmp_path)])
    assert code == 0
    data = json.loads(capsys.readouterr().out)
    assert data["mode"] == "quick" and data["command"].startswith("cfknode bench learning --quick")
    # Every row landed in the table but the wake's ceiling, which a single drone does not fly.
    assert sorted(r["controller"] for r in data["runs"]) == sorted(set(CONTROLLERS) - FLEET_ONLY)
    assert all(r["cell"] == QUICK_CELLS[0] and r["mse"] > 0.0 for r in data["runs"])
    md = (tmp_path / "learning_quick.md").read_text()
    assert md.count("| KNODE-MPC-Online") == 2 and md.count("| nominal MPC") == 1 and md.count("| MPC + layer |") == 1
    assert md.count("| MPC + layer + the plant's air (ceiling) |") == 1
    assert len((tmp_path / "learning_quick_runs.jsonl").read_text().splitlines()) == 5  # each flight as it landed


def test_a_crossing_cell_hovers_one_drone_over_the_other_s_line_for_ten_passes():
    from cfknode.flight.formation import fleet_references

    cell = BY_NAME["crossing dz=0.3 v=1"]
    cfg = load_config(overrides=cell.config("layer", 0, "/tmp"))
    assert cfg.fleet.layout == "crossing" and cfg.fleet.min_separation < cell.spacing
    (s_low, low), (s_high, high) = fleet_references(cfg.trajectory, 2, "crossing", 0.0, cfg.fleet.stack_spacing,
                                                    cfg.fleet.ground_spacing)
    passes = low.phase_times(math.pi)
    assert len(passes) == 10
    under, above = low.sample(passes), high.sample(passes)
    assert np.allclose(above.p - under.p, [0.0, 0.0, 0.3], atol=1e-6)  # right under the hovering drone
    assert np.all(np.abs(under.v[:, 0]) == pytest.approx(1.0, rel=1e-3))  # at the cell's speed
    assert s_high[1] - s_low[1] == pytest.approx(cfg.fleet.ground_spacing)  # they start side by side


def test_a_flight_that_could_not_fly_is_a_row_not_the_end_of_the_bench():
    cell = BY_NAME["circle r=0.5 v=1"]
    # A job whose config is refused (a seed out of range) stands for any flight that raises.
    run = run_job(Job(cell, "online", -5, "/tmp", 4.0))
    assert math.isnan(run.mse) and run.tripped and run.outcome.startswith("did not fly")
    ok = Run(cell.name, "layer", -5, 1e-4, 0.0, 0.01, False, False, "flight complete: landed", 0, 0, 1.0)
    md = markdown([cell], [], [ok, run], tuple(CONTROLLERS), "cmd", "0.1.0", "full", "dob")
    assert "| KNODE-MPC-Online (paper) | did not fly |" in md and "Did not fly (counted as trips)" in md
    assert math.isnan(ratio([ok, run], cell.name, "online", "layer"))


def test_rows_can_be_chosen_and_the_table_says_which():
    from cfknode.app.bench.learning import _command, select_rows
    from cfknode.app.errors import UsageError

    assert select_rows("") == tuple(CONTROLLERS)
    assert select_rows("air+layer, layer") == ("layer", "air+layer")  # the table's order, not the flag's
    with pytest.raises(UsageError, match="unknown row"):
        select_rows("layer,oracle")
    args = argparse.Namespace(quick=False, seeds=3, groups="", cells="", rows="layer,air+layer", duration=0.0,
                              fixed_latency=0.1, config="", set=[])
    assert "--rows 'layer,air+layer'" in _command(args, argparse.Namespace(command_flags=lambda: "--jobs 2"))


def test_the_ceiling_row_flies_the_plant_s_air_beside_the_layer():
    job = Job(BY_NAME["crossing dz=0.3 v=1"], "air+layer", 0, "/tmp", 4.0)
    cfg = load_config(overrides=flight_overrides(job))
    assert cfg.sim.air_model and cfg.fleet.neighbour_input and not cfg.online.enabled
    assert cfg.controller.adaptation == load_config().controller.adaptation  # the configured layer


def test_the_wake_s_ceiling_flies_the_plant_s_wake_in_the_fleet_cells_only():
    job = Job(BY_NAME["crossing dz=0.3 v=1"], "wake+layer", 0, "/tmp", 4.0)
    cfg = load_config(overrides=flight_overrides(job))
    assert cfg.sim.air_model and cfg.sim.air_model_terms == "wake" and cfg.fleet.neighbour_input
    assert not cfg.online.enabled
    # On a single drone's cell the row is left out (the quick bench above, which asks for every row, flies it
    # on no cell), not flown as the layer under another name.
    assert "wake+layer" in FLEET_ONLY and BY_NAME[QUICK_CELLS[0]].fleet == 1


def test_every_cell_can_be_named_on_the_command_line():
    assert all("," not in c.name for c in CELLS)  # --cells splits on commas
    assert [c.name for c in select_cells(_args(cells=",".join(c.name for c in CELLS)))] == [c.name for c in CELLS]


def test_a_config_file_becomes_every_flight_s_overrides_before_the_command_line_s(tmp_path):
    from pathlib import Path

    from cfknode.app.bench.learning import _command, _file_overrides
    from cfknode.app.config import ConfigError

    profile = Path(__file__).resolve().parents[1] / "cfknode" / "config" / "wake.yaml"  # a partial config
    extra = dict(_file_overrides(str(profile)))
    assert extra["online.layer_replay_windows"] == 9 and extra["online.gate_layer_min_pairs"] == 800
    job = Job(BY_NAME["vertical A=0.3 f=0.5"], "online+layer", 0, str(tmp_path), 2.0, tuple(extra.items()))
    cfg = load_config(overrides=flight_overrides(job))
    assert cfg.online.layer_filter_hz == 8.0 and cfg.online.gate_layer_min_gain == 0.01 and cfg.knode.queue_size == 1
    args = argparse.Namespace(quick=True, seeds=1, groups="", cells="", rows="", duration=0.0, fixed_latency=0.1,
                              config=str(profile), set=["online.layer_weight_decay=0.1"])
    executor = argparse.Namespace(command_flags=lambda: "--jobs 1")
    cmd = _command(args, executor)
    assert cmd.index("--config") < cmd.index("--set")  # the table's command reproduces the run
    bad = tmp_path / "bad.yaml"
    bad.write_text("online:\n  layer_replay_windows: many\n")
    with pytest.raises(ConfigError) as err:
        _file_overrides(str(bad))
    assert "\n" not in str(err.value)
    assert _file_overrides("") == ()
