"""Checks of a flight's configuration before anything is built or connected.

``refuse_unflyable(cfg)`` raises a one-line ``ConfigError`` (exit status 2 at the CLI) when:

- a hardware robot's values (mass, battery limits from the robots file) break the config bounds;
- the trajectory leaves the geofence's soft box, or needs more tilt or thrust than the limits
  allow (``cfknode/app/trajectory_fit.py``); with ``hardware.force`` it flies anyway, and the reason
  is returned as a log event instead;
- the log directory or the e-stop mailbox directory cannot be created or written, or the log
  directory has less free space than the flight's log is expected to need.

Cheap by design: it runs before the MPC is built and before any radio is opened.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

from cfknode.app.config import Config, ConfigError
from cfknode.app.config_bounds import check_bounds
from cfknode.safety.operator import mailbox_dir
from cfknode.app.trajectory_fit import trajectory_problem
from cfknode.flight.trajectory import make_trajectory

# A simulated flight's log took about 650 bytes per drone and control tick (lz4); rounded up
# for events, online-learning records and the index, plus a fixed part.
LOG_BYTES_PER_TICK = 1024
LOG_FIXED_BYTES = 1 << 20


def writable_dir_problem(path: Path, key: str) -> str | None:
    """Why the directory ``path`` (config key ``key``) cannot hold new files, or None; creates it."""
    if path.exists() and not path.is_dir():
        return f"{key} {path} is a file, not a directory"
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"{key} {path}: cannot create the directory ({exc.strerror or exc})"
    if not os.access(path, os.W_OK | os.X_OK):
        return f"{key} {path}: the directory is not writable"
    return None


def refuse_unflyable(cfg: Config, where: str = "") -> list[dict[str, Any]]:
    """Raise ``ConfigError`` if ``cfg`` must not fly; return the log events of a forced take-off.

    ``where`` names the source of values not from the config file (a robot from the robots file).
    """
    if where:
        check_bounds(cfg, where=f"{where}: ")
    for path, key in ((Path(cfg.log.dir).expanduser(), "log.dir"),
                      (mailbox_dir(cfg.safety.estop_dir), "safety.estop_dir")):
        problem = writable_dir_problem(path, key)
        if problem is not None:
            raise ConfigError(problem)
    problem = log_space_problem(cfg)
    if problem is not None:
        raise ConfigError(problem)
    events = thrust_margin_warnings(cfg)
    problem = trajectory_problem(cfg)
    if problem is None:
        return events
    if not cfg.hardware.force:
        raise ConfigError(f"refusing to take off: {problem} (hardware.force / --force flies it clamped)")
    return [*events, {"level": "warning", "text": f"take-off FORCED despite: {problem}", "source": "preflight"}]


def expected_log_bytes(cfg: Config) -> int:
    """About how many bytes this flight's log takes: every drone (a fleet's too), every tick of the
    whole reference (take-off to touch-down)."""
    drones = max(1, cfg.fleet.size)
    duration = make_trajectory(cfg.trajectory, cfg.sim.initial_position).duration
    return int(LOG_FIXED_BYTES + drones * duration * cfg.controller.rate_hz * LOG_BYTES_PER_TICK)


def log_space_problem(cfg: Config) -> str | None:
    """Why the log directory cannot hold this flight's log (one line), or None."""
    path = Path(cfg.log.dir).expanduser()
    try:
        free = shutil.disk_usage(path).free
    except OSError as exc:
        return f"log.dir {path}: cannot check its free space ({exc.strerror or exc})"
    need = expected_log_bytes(cfg)
    if free >= need:
        return None
    return (f"take-off refused: log.dir {path} has {free / 1e6:.1f} MB free, and this flight's log needs about "
            f"{need / 1e6:.1f} MB; free some space or point log.dir elsewhere")


LOW_THRUST_TO_WEIGHT = 1.3  # below this at the clamp, a payload or a sagging battery leaves no margin to climb


def thrust_margin_warnings(cfg: Config) -> list[dict[str, Any]]:
    """A warning (logged, and printed by the CLI) when the thrust the controller may plan is under
    1.3 times the weight, for the nominal vehicle and for the heaviest simulated mass step."""
    v, c = cfg.vehicle, cfg.controller
    usable = c.max_thrust_fraction * v.max_thrust
    factors = [1.0] + ([max(m.factor for m in cfg.sim.mass_changes)] if cfg.backend == "sim" and cfg.sim.mass_changes
                       else [])
    worst = max(factors)
    ratio = usable / (v.mass * worst * v.gravity)
    if ratio >= LOW_THRUST_TO_WEIGHT:
        return []
    what = "the vehicle" if worst == 1.0 else f"the vehicle at {worst:g}x mass"
    text = (f"thrust-to-weight at the thrust clamp is {ratio:.2f} for {what} (below {LOW_THRUST_TO_WEIGHT}): "
            "little margin to climb or to tilt; the controller keeps altitude before it tilts")
    return [{"level": "warning", "text": text, "source": "preflight"}]
