"""Which drones of a fleet learn the drone above alone, those whose reference passes under another's, and how.

A drone that flies through another's wake learns it best from where that drone is, not from its own velocity and
command, which the controller's answer to the wake also moves (docs/fleet.md#wake-only). A drone that never flies
under another keeps learning its own air. ``fleet.wake_below`` makes the choice per drone from the references,
before take-off, for networks that fly beside the fast layer; ``fleet.wake_only`` makes every drone's networks
wake networks. Either way such a drone learns with the wake's settings (``cfknode/config/wake.yaml``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np

from cfknode.app.config import Config, load_config, packaged_settings, with_defaults
from cfknode.app.learning import beside_layer
from cfknode.flight.adaptation.wake_guard import REACH_M

STEP_S = 0.02  # s between the reference samples compared (a 1.5 m/s pass crosses 0.15 m in 0.1 s)
RADIUS_M = 0.15  # m of horizontal distance within which a drone above's wake reaches the one below


def passes_under(ref: Any, others: Sequence[Any], radius: float = RADIUS_M, reach: float = REACH_M) -> bool:
    """Whether ``ref`` (a reference with ``duration`` and ``sample(t).p``) is ever under one of ``others``: within
    ``radius`` horizontally and below by less than ``reach``, at the same time."""
    if not others:
        return False
    duration = max(float(r.duration) for r in (ref, *others))
    t = np.arange(0.0, duration + STEP_S, STEP_S)
    p = np.asarray(ref.sample(t).p)
    for other in others:
        d = np.asarray(other.sample(t).p) - p
        if np.any((d[:, 2] > 0.0) & (d[:, 2] < reach) & (np.hypot(d[:, 0], d[:, 1]) < radius)):
            return True
    return False


def wake_below_configs(cfg: Config, configs: Sequence[Config], refs: Sequence[Any] | None) -> list[Config]:
    """``configs`` with the drones that learn a wake chosen and set to learn it, when the networks see the
    neighbour (``fleet.neighbour_input``) beside a fast layer, which keeps the drone's own mass and air (without
    one, as in the paper, a wake network would leave them unlearned).

    ``fleet.wake_below`` chooses each drone whose reference passes under another's, where ``refs`` are known before
    take-off (None: a fleet of robots, placed where the mocap sees them); ``fleet.wake_only`` chooses every drone.
    A chosen drone flies the wake's learning settings (``cfknode/config/wake.yaml``) wherever its
    config keeps the default: a wake is a few centimetres wide and crossed in a tenth of a second.
    """
    f = cfg.fleet
    if not (f.neighbour_input and beside_layer(cfg)):
        return list(configs)
    settings, default = packaged_settings("wake"), load_config()
    out = []
    for i, c in enumerate(configs):
        others = [] if refs is None or not f.wake_below or c.fleet.wake_only else [*refs[:i], *refs[i + 1:]]
        if others and passes_under(refs[i], others):
            c = dataclasses.replace(c, fleet=dataclasses.replace(c.fleet, wake_only=True))
        out.append(with_defaults(c, settings, default) if c.fleet.wake_only else c)
    return out


__all__ = ["passes_under", "wake_below_configs"]
