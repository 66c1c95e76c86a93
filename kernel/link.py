"""The radio link as the host sees it."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable


@dataclass(frozen=True)
class LinkStatus:
    """The radio link as the host sees it.

    ``lost``: cflib's ``connection_lost`` message (the link is gone for good), else None.
    ``silence_s``: time since the drone last acknowledged a packet (0 when unknown).
    ``latency_s``: round trip of cflib's link-statistics pings (NaN when unknown).
    """

    lost: str | None = None
    silence_s: float = 0.0
    latency_s: float = math.nan


LINK_OK = LinkStatus()
LinkSource = Callable[[float], LinkStatus]
