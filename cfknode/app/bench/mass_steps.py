"""The paper's mass-change protocol on the flight stack, shared by the benches that fly it.

Mass 0.5x nominal 2 s after the pattern starts, then 1.33x at 5 s (the paper's times; a
shortened smoke-test pattern scales them). The offline KNODE-MPC is trained, as the paper
does, on a nominal-MPC flight that saw only the first change.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

FIRST_FACTOR = 0.5
SECOND_FACTOR = 1.33
PAPER_STEPS = ((2.0, FIRST_FACTOR), (5.0, SECOND_FACTOR))  # (s after the pattern starts, mass / nominal)


@dataclass(frozen=True)
class MassSchedule:
    first: tuple[dict[str, float], ...]  # only the first change (the offline model's training flight)
    both: tuple[dict[str, float], ...]  # every change: the evaluation flights


def mass_schedule(overrides: dict[str, Any], at: tuple[float, ...] = (2.0, 5.0),
                  factors: tuple[float, ...] = (FIRST_FACTOR, SECOND_FACTOR)) -> MassSchedule:
    """Changes to ``factors`` at ``at`` seconds after the pattern of the configured trajectory starts."""
    from cfknode.app.config import load_config
    from cfknode.flight.trajectory import make_trajectory

    cfg = load_config(overrides=overrides)
    t0 = make_trajectory(cfg.trajectory, np.asarray(cfg.sim.initial_position, dtype=float)).segments["pattern"][0]
    changes = tuple({"t": t0 + t, "factor": f} for t, f in zip(at, factors, strict=True))
    return MassSchedule(changes[:1], changes)


def train_offline_model(overrides: dict[str, Any], schedule: MassSchedule, out: Path, name: str) -> Path:
    """Fly nominal MPC through the first change only, then ``cfknode train`` on that log (with the overrides'
    ``training.*`` settings); returns the model path."""
    from cfknode.app.config import load_config
    from cfknode.app.mission import run_flight

    flight = run_flight(load_config(overrides={**overrides, "sim.mass_changes": list(schedule.first)}),
                        name_hint=f"{name}-first-change")
    if flight.summary.log_path is None:
        raise RuntimeError(f"{name}: the training flight wrote no log")
    model = out / f"{name}-offline.ckpt"
    # The cell's own training settings reach the model trained for it (JSON is YAML: --set reads it).
    settings = [f"--set={key}={json.dumps(value)}" for key, value in overrides.items() if key.startswith("training.")]
    done = subprocess.run([sys.executable, "-m", "cfknode", "train", "--log", flight.summary.log_path, "--out", str(model),
                           *settings], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{name}: cfknode train failed: {(done.stderr or done.stdout).strip().splitlines()[-1:]}")
    return model


# What each compared controller adds to the cell's overrides (given the offline model's path).
# The rows without the fast layer say so: the configured default has it on.
_NO_LAYER = {"controller.adaptation": "none"}
CONTROLLER_OVERRIDES: dict[str, Any] = {
    "nominal": lambda model: dict(_NO_LAYER),
    "offline": lambda model: {"controller.model": str(model), **_NO_LAYER},
    "geometric": lambda model: {"controller.kind": "geometric", **_NO_LAYER},
    "online": lambda model: {"online.enabled": True, **_NO_LAYER},
    "dob": lambda model: {"controller.adaptation": "dob"},
    "online_dob": lambda model: {"online.enabled": True, "controller.adaptation": "dob"},
    "oracle": lambda model: {"controller.adaptation": "oracle"},  # a reference: the true mass every tick
    # The same, 20 ms late: what an estimator that needs two mocap frames to see a change could at best do.
    "oracle_late": lambda model: {"controller.adaptation": "oracle", "controller.adaptation_settings.oracle_delay_s": 0.02},
}


__all__ = ["CONTROLLER_OVERRIDES", "FIRST_FACTOR", "MassSchedule", "PAPER_STEPS", "SECOND_FACTOR", "mass_schedule",
           "train_offline_model"]
