"""Settings of a fleet flight (``fleet:`` in the config; ``cfknode fly --fleet N``; docs/fleet.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from cfknode.kernel.setting import setting


@dataclass(frozen=True)
class FleetConfig:
    size: int = setting(unit="drones", low=0, high=16, doc="0 or 1 flies one drone")
    layout: Literal["ring", "stack", "crossing"] = setting(
        doc="ring: spaced around the circle; stack: heights stack_spacing apart; crossing: 2nd hovers over 1st's line")
    stack_spacing: float = setting(unit="m", low=0, high=5, open_low=True, doc="between stacked heights")
    ground_spacing: float = setting(unit="m", low=0, high=5, open_low=True,
        doc="between stacked drones' start positions")
    min_separation: float = setting(unit="m", low=0, high=5,
        doc="m (0: off); Crazyswarm's downwash ellipsoid is 0.12 m wide and 0.3 m tall")
    hold_s: float = setting(unit="s", low=0, high=10, doc="s a pair that came too close hovers in place before landing")
    on_fault: Literal["land_all", "continue", "hold"] = setting(
        doc="land_all | continue | hold: what the others do when one drone's flight fails")
    radio_budget_pps: float = setting(unit="packets/s", low=50, high=2000,
        doc="packets/s per Crazyradio in each direction (docs/hardware.md#radio-budget)")
    ping_hz: float = setting(unit="Hz", low=0, high=100, doc="cflib's link-statistics ping (every 100 ms) on each link")
    drones_per_sim_radio: int = setting(unit="drones", low=1, high=16,
        doc="sim://N shares simulated radio N // 2 (the budget applies to it as to a real one)")
    name_prefix: str = setting(doc="drones cf1, cf2, ...: log channels /cf1/state, e-stop names sim-cf1")
    neighbour_input: bool = setting(
        doc="online learning: each drone's model also sees where the nearest drone above is (docs/fleet.md#neighbour-input)")
    wake_only: bool = setting(
        doc="with neighbour_input: the model sees only that, not the drone's own velocity and command (docs/fleet.md#wake-only)")
    wake_below: bool = setting(
        doc="beside the layer: wake_only and config/wake.yaml for drones passing under another "
            "(docs/fleet.md#wake-only)")
    ray_radio_resource: str = setting(
        doc="--executor ray: the Ray resource of the node with the drone's radio (docs/fleet-ray.md)")
