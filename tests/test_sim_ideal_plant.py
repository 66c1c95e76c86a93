"""``sim.aero: ideal`` is the plant as it was before the realistic terms existed, to the bit.

The fixture ``tests/data/ideal_plant_trajectory.json`` was written by ``python
tests/test_sim_ideal_plant.py --write`` on the code before ``sim.aero`` existed (git 0aca553):
a take-off from the ground, manoeuvres, a mass change, drag with wind and a touchdown through
the simulated firmware and plant. Every 10 ms state (17 floats) goes into its SHA-256; every
0.1 s one is kept in hex so that a mismatch shows where the plants part.
"""

from __future__ import annotations

import hashlib
import json
import struct
import sys
from pathlib import Path

from cfknode.app.config import load_config
from cfknode.sim_backend.crazyflie import SimCrazyflie

FIXTURE = Path(__file__).parent / "data" / "ideal_plant_trajectory.json"
TX = 0.01
# (duration s, roll deg, pitch deg, yaw rate deg/s, thrust as a fraction of the hover command)
PHASES = ((0.02, 0.0, 0.0, 0.0, 0.0), (0.5, 0.0, 0.0, 0.0, 1.2), (0.4, 6.0, -4.0, 30.0, 0.95),
          (0.5, -5.0, 8.0, -40.0, 0.9), (0.4, 0.0, 0.0, 0.0, 0.9), (1.3, 0.0, 0.0, 0.0, 0.75))
OVERRIDES = {"sim.aero": "ideal", "sim.drag": [0.004, 0.005, 0.003], "sim.wind": [0.6, -0.4, 0.1],
             "sim.mass_changes": [{"t": 1.2, "factor": 1.1}]}


def ideal_trajectory(overrides: dict | None = None) -> tuple[str, list[list[str]]]:
    """(SHA-256 of every 10 ms 17-state, the 0.1 s states in hex) of the scripted flight."""
    cfg = load_config(overrides={**OVERRIDES, **(overrides or {})})
    sim = SimCrazyflie(cfg.vehicle, cfg.sim)
    hover = sim.mass * cfg.vehicle.gravity / cfg.vehicle.newton_per_cmd
    digest = hashlib.sha256()
    kept: list[list[str]] = []
    n = 0
    for duration, roll, pitch, yawrate, thrust in PHASES:
        end = sim.t + duration - 1e-9
        while sim.t < end:
            sim.firmware.on_rpyt(sim.t, roll, -pitch, yawrate, round(thrust * hover))
            sim.step_to(sim.t + TX)
            x = sim.vehicle.state_list()
            digest.update(struct.pack("<17d", *x))
            n += 1
            if n % 10 == 0:
                kept.append([v.hex() for v in x])
    return digest.hexdigest(), kept


def test_the_ideal_plant_reproduces_the_recorded_trajectory_bit_for_bit():
    want = json.loads(FIXTURE.read_text())
    digest, kept = ideal_trajectory({"sim.aero": "ideal"})
    for i, (a, b) in enumerate(zip(kept, want["kept"])):
        assert a == b, f"the plants part by t = {0.1 * (i + 1):.1f} s"
    assert digest == want["sha256"]


def test_the_default_mission_on_the_ideal_plant_flies_its_recorded_mse_to_the_bit(tmp_path):
    """The README's first command on the ideal plant (`--set sim.aero=ideal`, the paper-protocol plant) flies the
    MSE it flew when that plant was the default (docs/results.md#default-mission)."""
    from cfknode.app.mission import run_flight

    cfg = load_config(overrides={"sim.aero": "ideal", "log.dir": str(tmp_path), "safety.estop_dir": str(tmp_path)})
    assert run_flight(cfg).summary.mse == 2.581807478719663e-06


def test_the_recorded_flight_leaves_the_ground_manoeuvres_and_lands():
    kept = json.loads(FIXTURE.read_text())["kept"]
    z = [float.fromhex(row[2]) for row in kept]
    assert max(z) > 0.3 and z[-1] == 0.0


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    FIXTURE.parent.mkdir(exist_ok=True)
    sha, rows = ideal_trajectory()
    FIXTURE.write_text(json.dumps({"sha256": sha, "kept": rows}, indent=0) + "\n")
