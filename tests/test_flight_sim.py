"""Closed-loop lockstep flights through the whole stack: cflib -> sim:// -> simulated firmware."""

import json
import subprocess
import sys

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.app.logs.writer import read_log
from cfknode.app.mission import run_flight

# A short version of the default mission: same circle, fewer seconds on it.
SHORT = {
    "trajectory.duration": 6.0,
    "trajectory.takeoff_duration": 2.0,
    "trajectory.settle_duration": 0.5,
    "trajectory.land_duration": 2.0,
    "trajectory.ramp_duration": 1.0,
}


def _fly(tmp_path, **overrides):
    cfg = load_config(overrides={**SHORT, "log.dir": str(tmp_path), **overrides})
    return run_flight(cfg, name_hint="test")


@pytest.fixture(scope="module")
def circle(tmp_path_factory):
    return _fly(tmp_path_factory.mktemp("circle"))


def test_circle_tracks_within_bound(circle):
    s = circle.summary
    assert s.window_samples > 2000
    assert s.mse < 5e-4, s.mse
    assert s.max_error < 0.05
    assert s.extra["fallback_ticks"] == 0
    assert s.ticks == circle.record.ticks


def test_circle_is_reproducible_with_a_seed(circle, tmp_path):
    again = _fly(tmp_path)
    np.testing.assert_array_equal(again.record.p, circle.record.p)
    np.testing.assert_array_equal(again.record.p_ref, circle.record.p_ref)


def test_a_different_seed_changes_the_noise(circle, tmp_path):
    other = _fly(tmp_path, **{"sim.seed": 7})
    assert not np.array_equal(other.record.p, circle.record.p)
    assert other.summary.mse < 5e-4


def test_flight_log_holds_the_flight(circle):
    log = read_log(circle.summary.log_path)
    assert not log.truncated
    assert log.config["trajectory"]["radius"] == 0.5
    n = len(log.topic("/tick"))
    assert n == circle.record.ticks
    assert len(log.topic("/mocap")) > 0.9 * 100 * circle.record.t[-1]
    assert log.topic("/summary")[0]["mse"] == pytest.approx(circle.summary.mse)
    sources = set(log.array("/command", "source"))
    assert {"mpc", "cutoff"} <= sources


def test_hover_holds_position(tmp_path):
    res = _fly(tmp_path, **{"trajectory.kind": "hover", "trajectory.duration": 3.0})
    assert res.summary.max_error < 0.02
    assert res.summary.mse < 2e-5


def test_geometric_controller_flies_too(tmp_path):
    res = _fly(tmp_path, **{"controller.kind": "geometric"})
    # The firmware's Mellinger gains are soft: it flies the circle, with more lag than the MPC.
    assert res.summary.mse < 5e-3
    assert res.summary.extra["solver"] == "none"


def test_mass_change_is_survived(tmp_path):
    res = _fly(tmp_path, **{"sim.mass_changes": [{"t": 4.0, "factor": 1.2}]})
    assert res.summary.max_error < 0.15


def test_cli_fly_json_end_to_end(tmp_path):
    cmd = [sys.executable, "-m", "cfknode", "fly", "--traj", "circle", "--radius", "0.5", "--json",
           "--log-dir", str(tmp_path)] + [f"--set={k}={v}" for k, v in SHORT.items()]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["mse"] < 5e-4
    assert summary["log_path"].startswith(str(tmp_path))


def test_cli_fly_ends_with_a_summary_read_at_a_glance(tmp_path, monkeypatch, capsys):
    from cfknode.app.cli import main

    # The default mission, shorter on the circle (the rows depend on its parts, not its length).
    monkeypatch.chdir(tmp_path)
    assert main(["fly", "--headless", "--log-dir", "flights", *[f"--set={k}={v}" for k, v in SHORT.items()]]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("cfknode fly: sim, circle") and lines[-1] == "cfknode: flight complete: landed"
    summary = lines[1:]
    assert len(summary) <= 12, summary
    assert max(map(len, lines)) <= 80, lines
    assert any("mass estimate" in line for line in summary)


def test_mission_hands_the_firmware_back_landed_not_locked(circle):
    assert circle.summary.extra["firmware_after_shutdown"] == "landed"


def test_realtime_flight_on_the_wall_clock(tmp_path):
    res = _fly(
        tmp_path,
        **{
            "sim.realtime": True,
            "trajectory.kind": "hover",
            "trajectory.duration": 0.5,
            "trajectory.takeoff_duration": 1.0,
            "trajectory.settle_duration": 0.2,
            "trajectory.land_duration": 1.0,
        },
    )
    s = res.summary
    # Wall time is at least the simulated time: the loop really waited for the clock.
    assert s.wall_time_s >= s.duration_s - 0.05
    # Ticks keep the 400 Hz slots, one at most in each, and a slot whose window passed is passed over rather
    # than queued, so how many run depends on the machine's load; that the loop keeps its slots does not.
    t = np.asarray(res.record.t)
    slots = np.floor(t / 0.0025 + 1e-6)
    assert np.all(np.diff(slots) >= 1)  # each 2.5 ms slot at most once
    assert s.skipped_slots == int((np.diff(slots) - 1).sum())  # counted live as the ticks' times say
    assert s.ticks > 0.25 * 400 * s.duration_s  # a stalled loop, not a busy machine
    assert s.max_error < 0.05
