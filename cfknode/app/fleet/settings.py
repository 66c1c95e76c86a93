"""Settings of a fleet flight (``fleet:`` in the config; ``cfknode fly --fleet N``; docs/fleet.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class FleetConfig:
    size: int  # drones; 0 or 1 is the single-drone flight (``--fleet N`` sets it)
    layout: Literal["ring", "stack"]  # ring: evenly spaced phases on one circle; stack: same circle, stacked heights
    stack_spacing: float  # m between the heights of stacked drones
    ground_spacing: float  # m between stacked drones' start positions (side by side on the ground)
    min_separation: float  # m: refused before take-off if the references come closer; held and landed in flight
    hold_s: float  # s a pair that came too close hovers in place before it lands
    on_fault: Literal["land_all", "continue", "hold"]  # what the other drones do when one drone's flight fails
    radio_budget_pps: float  # packets/s one radio carries in each direction (docs/hardware.md#radio-budget)
    ping_hz: float  # cflib's link-statistics ping, per link
    drones_per_sim_radio: int  # simulated radios: sim://N is on simulated radio N // drones_per_sim_radio
    name_prefix: str  # drone names: <prefix>1, <prefix>2, ... (log channels /cf1/state, e-stop sim-cf1)
    ray_radio_resource: str  # --executor ray: the Ray resource a drone's actor needs; "{radio}" is its radio index
