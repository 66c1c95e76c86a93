"""Small building blocks of the supervisor's watchdogs: persistence timers, a low-pass filter,
tilt from a quaternion, and the radio link's health.

They run every tick (or every few), so they are plain Python on floats: no numpy, no allocation.
"""

from __future__ import annotations

import math
from typing import Any

from cfknode.kernel.link import LinkSource, LinkStatus




def radio_link_status(radio: Any) -> LinkSource:
    """Link health from a radio's ``stats()`` (``CflibRadio``): ``link_lost`` always, and the
    ping latency when the radio reports one (``latency_ms``, from cflib's link statistics)."""

    def status(now: float) -> LinkStatus:
        stats = radio.stats()
        latency_ms = getattr(stats, "latency_ms", None)
        latency = math.nan if latency_ms is None else float(latency_ms) * 1e-3
        return LinkStatus(lost=stats.link_lost, silence_s=0.0, latency_s=latency)

    return status


def worst_link(*sources: LinkSource) -> LinkSource:
    """One link source from several (the radio's own, an injected fault): the worst of each field."""

    def status(now: float) -> LinkStatus:
        lost, silence, latency = None, 0.0, math.nan
        for source in sources:
            s = source(now)
            lost = lost or s.lost
            silence = max(silence, s.silence_s)
            if not math.isnan(s.latency_s):
                latency = s.latency_s if math.isnan(latency) else max(latency, s.latency_s)
        return LinkStatus(lost, silence, latency)

    return status


class Persistence:
    """True once a condition has held continuously for ``duration`` seconds (0: at once)."""

    __slots__ = ("duration", "since")

    def __init__(self, duration: float) -> None:
        self.duration = duration
        self.since: float | None = None

    def update(self, now: float, condition: bool) -> bool:
        if not condition:
            self.since = None
            return False
        if self.since is None:
            self.since = now
        return now - self.since >= self.duration - 1e-9


class LowPass:
    """First-order low-pass with time constant ``tau``; the first sample initialises it."""

    __slots__ = ("tau", "value", "_t")

    def __init__(self, tau: float) -> None:
        self.tau = tau
        self.value = math.nan
        self._t = math.nan

    def update(self, t: float, x: float) -> float:
        if math.isnan(self.value):
            self.value = x
        else:
            alpha = min(max(t - self._t, 0.0) / self.tau, 1.0)
            self.value += alpha * (x - self.value)
        self._t = t
        return self.value


def tilt_cos(qw: float, qx: float, qy: float, qz: float) -> float:
    """Cosine of the angle between the body z axis and world up (R[2, 2]) for a unit quaternion."""
    return 1.0 - 2.0 * (qx * qx + qy * qy)


def tilt_deg(q: Any) -> float:
    """Tilt from level, degrees, of a scalar-first quaternion."""
    w, x, y, z = (float(c) for c in q)
    c = tilt_cos(w, x, y, z)
    return math.degrees(math.acos(min(max(c, -1.0), 1.0)))
