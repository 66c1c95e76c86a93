"""Thrust calibration: the hover estimate from logged commands, and a calibration flight against the
simulator with a mass the robots file does not know."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from cfknode.app.backends.calibrate import (
    CalibrationError,
    calibrate,
    calibration_config,
    estimate_hover,
    hover_window,
)
from cfknode.app.config import ConfigError, load_config
from cfknode.app.logs.writer import FlightLog, read_log
from cfknode.app.backends.robots import load_robot
from test_hardware_backend import SHORT_HOVER, fly_cf, robots_file

G = 9.81
NPC = 4 * 0.12 / 65535  # N per thrust command


def synthetic_log(tmp_path: Path, hover: float, *, tilt_deg: float = 5.0, saturate: bool = False) -> Path:
    """Ticks at 400 Hz: a climb (fast, excluded), then hover with a constant tilt and thrust noise."""
    rng = np.random.default_rng(3)
    half = np.radians(tilt_deg) / 2
    q = [np.cos(half), np.sin(half), 0.0, 0.0]
    with FlightLog.create(tmp_path, {}, "test", "synthetic") as log:
        for k in range(2000):
            t = k / 400.0
            climbing = t < 1.0
            v = [0.0, 0.0, 0.5 if climbing else 0.01 * rng.standard_normal()]
            thrust = 60000 if (saturate and k == 1500) else hover / np.cos(2 * half) + 300 * rng.standard_normal()
            if climbing:
                thrust *= 1.2
            log.write("/state", t, {"p": [0.0, 0.0, 0.5], "v": v, "q": q})
            log.write("/command", t, {"acc": [0.0, 0.0, 0.0], "roll_deg": 0.0, "pitch_deg": 0.0,
                                      "yawrate_deg": 0.0, "thrust": int(round(thrust)), "source": "mpc"})
            if k % 100 == 0:
                log.write("/command", t + 1e-4, {"acc": [0, 0, 0], "roll_deg": 0, "pitch_deg": 0, "yawrate_deg": 0,
                                                 "thrust": 0, "source": "cutoff"})  # no state at that time: ignored
    return log.path


def test_hover_estimate_from_logged_commands(tmp_path: Path) -> None:
    log = read_log(synthetic_log(tmp_path, hover=42000.0))
    est = estimate_hover(log, (0.5, 5.0), NPC, G)
    # Only the hover ticks count: the climb is too fast; the tilt is taken out with R33.
    assert est.samples == 1600
    assert est.window[0] == pytest.approx(1.0)
    assert est.hover_thrust == pytest.approx(42000, rel=2e-3)
    assert est.mass == pytest.approx(NPC * 42000 / G, rel=2e-3)
    assert est.newton_per_cmd == NPC and abs(est.vertical_acc) < 0.01
    assert 250 < est.thrust_std < 350


def test_estimate_refuses_a_saturated_or_unsteady_hover(tmp_path: Path) -> None:
    log = read_log(synthetic_log(tmp_path, hover=42000.0, saturate=True))
    with pytest.raises(CalibrationError, match="reached the clamp"):
        estimate_hover(log, (0.5, 5.0), NPC, G)
    with pytest.raises(CalibrationError, match="only 0 steady-hover ticks in 0.1-0.9 s"):
        estimate_hover(log, (0.1, 0.9), NPC, G)  # only the climb


def test_calibration_flies_a_hover_and_needs_a_robots_file() -> None:
    cfg = load_config(overrides={"trajectory.kind": "circle", "trajectory.duration": 30.0})
    hover = calibration_config(cfg, height=0.6, hover_s=3.0)
    assert (hover.trajectory.kind, hover.trajectory.height, hover.trajectory.duration, hover.backend) == (
        "hover", 0.6, 3.0, "cf")
    t0, t1 = hover_window(hover)
    start = hover.trajectory.takeoff_duration + hover.trajectory.settle_duration
    assert t0 == pytest.approx(start + 0.9) and t1 == pytest.approx(start + 3.0)

    flown: list[str] = []
    with pytest.raises(ConfigError, match="set hardware.robots_file"):
        calibrate(cfg, fly=lambda c, name: flown.append(name))
    assert flown == []  # refused before flying


def test_calibration_against_the_simulator_finds_the_true_mass(tmp_path: Path) -> None:
    path, _ = robots_file(tmp_path)
    robot = load_robot(path, "cf_sim")
    true_mass = 1.10 * robot.mass  # 10 % heavier than the robots file says (a deck, markers)
    cfg = load_config(overrides={
        "backend": "cf", "hardware.robot": "cf_sim", "hardware.robots_file": str(path), "log.dir": str(tmp_path),
        **SHORT_HOVER, "trajectory.takeoff_duration": 1.5, "hardware.heartbeat_hz": 0.0,
        "vehicle.mass": true_mass,  # the simulator's physics; the stack believes the robots file
    })
    before = path.read_text()
    result = calibrate(cfg, height=0.4, hover_s=2.5, fly=fly_cf)
    est = result.estimate
    assert est.mass == pytest.approx(true_mass, rel=0.02)
    assert est.hover_thrust == pytest.approx(true_mass * G / robot.newton_per_cmd, rel=0.02)
    assert est.samples >= 400
    assert result.previous_mass == robot.mass and result.previous_hover_thrust is None
    # Written into the robot's own entry; the rest of the file is as it was.
    updated = load_robot(path, "cf_sim")
    assert (updated.mass, updated.hover_thrust) == (result.written["mass"], result.written["hover_thrust"])
    assert updated.newton_per_cmd == pytest.approx(robot.newton_per_cmd, rel=1e-4)  # same mapping, now measured
    after = yaml.safe_load(path.read_text())
    assert after["robots"]["cf_sim"].pop("mass") == result.written["mass"]
    assert after["robots"]["cf_sim"].pop("hover_thrust") == result.written["hover_thrust"]
    assert after == yaml.safe_load(before)
    added = set(path.read_text().splitlines()) - set(before.splitlines())
    assert len(added) == 2 and all("cfknode calibrate" in line for line in added)
    assert "hover thrust" in result.message and str(path) in result.message
