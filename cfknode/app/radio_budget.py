"""The radio budget of a fleet: which drones share a Crazyradio, and whether it can carry them.

One Crazyradio carries about 500 packets/s in each direction (docs/hardware.md#radio-budget).
Each drone's link needs, uplink, its setpoints (``radio.tx_rate_hz``), one extpose per mocap
frame (the mocap rate) and cflib's link-statistics ping (``fleet.ping_hz``); every uplink
packet is acknowledged, so the downlink carries as many. A fleet whose drones on one radio
need more is refused before take-off, with the numbers.

Which radio: ``radio://R/...`` is Crazyradio R (cflib's device index). A simulated ``sim://N``
is on simulated radio ``N // fleet.drones_per_sim_radio``, so a simulated fleet is held to
the same budget as the radios it stands for (docs/fleet.md#radio-budget).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Sequence

from cfknode.kernel.errors import ConfigError

_RADIO = re.compile(r"radio://(\d+)/")
_SIM = re.compile(r"sim://(\d+)")


@dataclass(frozen=True)
class LinkLoad:
    name: str  # the drone
    uri: str
    setpoint_hz: float
    pose_hz: float
    ping_hz: float

    @property
    def packets_per_s(self) -> float:
        return self.setpoint_hz + self.pose_hz + self.ping_hz


def radio_of(uri: str, drones_per_sim_radio: int) -> str:
    """The radio a URI's link goes through: ``radio 0`` (a Crazyradio) or ``sim radio 1``."""
    m = _RADIO.match(uri)
    if m is not None:
        return f"radio {int(m.group(1))}"
    m = _SIM.match(uri)
    if m is not None:
        return f"sim radio {int(m.group(1)) // drones_per_sim_radio}"
    raise ConfigError(f"cannot tell which radio carries {uri!r} (expected radio://R/... or sim://N)")


def radio_index(uri: str, drones_per_sim_radio: int) -> int:
    """The index of the radio a URI's link goes through (Crazyradio R, or simulated radio N // per-radio)."""
    m = _RADIO.match(uri)
    if m is not None:
        return int(m.group(1))
    m = _SIM.match(uri)
    if m is not None:
        return int(m.group(1)) // drones_per_sim_radio
    raise ConfigError(f"cannot tell which radio carries {uri!r} (expected radio://R/... or sim://N)")


def radio_loads(loads: Sequence[LinkLoad], drones_per_sim_radio: int) -> dict[str, list[LinkLoad]]:
    """The links grouped by the radio that carries them, radios in first-use order."""
    out: dict[str, list[LinkLoad]] = {}
    for load in loads:
        out.setdefault(radio_of(load.uri, drones_per_sim_radio), []).append(load)
    return out


def check_radio_budget(loads: Sequence[LinkLoad], budget_pps: float, drones_per_sim_radio: int) -> dict[str, float]:
    """Packets/s per radio; ``ConfigError`` (one line, with the numbers) for a radio over ``budget_pps``."""
    totals = {}
    for radio, links in radio_loads(loads, drones_per_sim_radio).items():
        total = sum(link.packets_per_s for link in links)
        totals[radio] = total
        if total > budget_pps + 1e-9:
            each = " + ".join(f"{link.name} {link.packets_per_s:g}" for link in links)
            first = links[0]
            raise ConfigError(
                f"take-off refused: {radio} would carry {total:g} packets/s ({each}; each link "
                f"{first.setpoint_hz:g} setpoints + {first.pose_hz:g} poses + {first.ping_hz:g} pings), over its "
                f"budget of {budget_pps:g}/s: lower radio.tx_rate_hz or the mocap rate, or spread the drones "
                f"over more radios")
    return totals


__all__ = ["LinkLoad", "check_radio_budget", "radio_index", "radio_loads", "radio_of"]
