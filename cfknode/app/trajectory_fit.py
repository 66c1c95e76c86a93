"""Whether a trajectory can be flown as planned: inside the geofence and within the limits.

The supervisor clamps every reference into the fence's soft box while flying (see
``geofence.clamp_reference``), and the MPC clips accelerations to its box, so an unfit
trajectory is silently flown as a different one (a 4.9 m circle flown at 1.8 m). These
checks find that before take-off instead, from the trajectory's own samples:

- every position from the end of the take-off to the start of the landing lies in the soft box;
- every acceleration on the pattern (a circle of radius r at speed v needs v^2 / r sideways)
  needs a tilt and a collective thrust inside ``HEADROOM`` of what the controller may command.

Take-off and landing are smooth steps that the controller may lag behind briefly; they are
not judged here. All functions are pure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from cfknode.app.config import Config
from cfknode.flight.trajectory import Trajectory, make_trajectory
from cfknode.safety.geofence import Geofence

# The reference may use this fraction of the tilt and of the thrust above hover: the rest is
# left to feedback, which must correct errors while the reference is at its peak.
HEADROOM = 0.8
_MAX_SAMPLES = 200_000
_SAMPLE_DT = 0.005  # s; a 1 s circle period still gets 200 samples


@dataclass(frozen=True)
class FitLimits:
    tilt_deg: float  # the controller's tilt limit
    thrust_accel: float  # m/s^2, highest collective thrust per unit mass the controller may plan
    gravity: float


def fit_limits(cfg: Config) -> FitLimits:
    v = cfg.vehicle
    return FitLimits(cfg.controller.max_tilt_deg, cfg.controller.max_thrust_fraction * v.max_thrust / v.mass, v.gravity)


def _describe(cfg: Config) -> str:
    t = cfg.trajectory
    if t.kind == "hover":
        return f"hover at {t.height:g} m"
    return f"{t.kind} r={t.radius:g} m at {t.speed:g} m/s, {t.height:g} m high"


def _sample(traj: Trajectory, t0: float, t1: float) -> np.ndarray:
    n = int(min(_MAX_SAMPLES, max(2, math.ceil((t1 - t0) / _SAMPLE_DT) + 1)))
    return np.linspace(t0, t1, n)


def fence_problem(cfg: Config, traj: Any, what: str = "the trajectory") -> str | None:
    """The first axis on which the flown part of the reference leaves the soft box, as one line;
    ``what`` names it (a fleet drone's placed trajectory)."""
    fence = Geofence.from_config(cfg.safety)
    t0 = traj.segments["settle_start"][0]
    t1 = traj.segments["land"][0]
    p = traj.sample(_sample(traj, t0, t1)).p
    lo, hi = fence.soft_lo, fence.soft_hi
    for i, axis in enumerate("xyz"):
        if p[:, i].max() > hi[i] + 1e-9:
            return (f"{what} ({_describe(cfg)}) reaches {axis} = {p[:, i].max():.2f} m, beyond the fence's "
                    f"{hi[i]:.2f} m (safety.fence_max {axis} {fence.hi[i]:g} m - safety.fence_margin "
                    f"{fence.margin:g} m)")
        if p[:, i].min() < lo[i] - 1e-9:
            inset = f" + safety.fence_margin {fence.margin:g} m" if i < 2 else ""
            return (f"{what} ({_describe(cfg)}) reaches {axis} = {p[:, i].min():.2f} m, beyond the fence's "
                    f"{lo[i]:.2f} m (safety.fence_min {axis} {fence.lo[i]:g} m{inset})")
    return None


def limits_problem(cfg: Config, traj: Trajectory, limits: FitLimits) -> str | None:
    """Tilt and thrust the pattern's accelerations need, against ``HEADROOM`` of the limits, as one line."""
    t0, t1 = traj.pattern_window
    if t1 <= t0:
        return None
    a = traj.sample(_sample(traj, t0, t1)).a
    vertical = limits.gravity + a[:, 2]
    sideways = np.hypot(a[:, 0], a[:, 1])
    tilt = np.degrees(np.arctan2(sideways, vertical))
    tilt_cap = math.degrees(math.atan(HEADROOM * math.tan(math.radians(limits.tilt_deg))))
    if tilt.max() > tilt_cap:
        return (f"the trajectory ({_describe(cfg)}) needs {sideways.max():.2f} m/s^2 sideways, a {tilt.max():.1f} deg "
                f"tilt; controller.max_tilt_deg {limits.tilt_deg:g} deg leaves {tilt_cap:.1f} deg for the reference")
    thrust = np.hypot(sideways, vertical)
    thrust_cap = limits.gravity + HEADROOM * (limits.thrust_accel - limits.gravity)
    if thrust.max() > thrust_cap:
        return (f"the trajectory ({_describe(cfg)}) needs {thrust.max():.2f} m/s^2 of thrust; the thrust clamp "
                f"(controller.max_thrust_fraction, vehicle) leaves {thrust_cap:.2f} m/s^2 for the reference")
    return None


def trajectory_problem(cfg: Config) -> str | None:
    """Why ``cfg``'s trajectory cannot be flown as planned (one line), or None.

    The start position only shapes the take-off, which is not judged, so the configured
    ``sim.initial_position`` serves for hardware too.
    """
    traj = make_trajectory(cfg.trajectory, cfg.sim.initial_position)
    return fence_problem(cfg, traj) or limits_problem(cfg, traj, fit_limits(cfg))
