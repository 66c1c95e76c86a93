"""A fixed-period send schedule that never bursts: the radio's setpoint and heartbeat slots."""

from __future__ import annotations

import math

TIME_EPS = 1e-9  # s; tick times built as k * period must not miss a slot to rounding


class Cadence:
    """Due every ``period`` seconds on whatever clock the caller passes in.

    A caller that falls behind (or the first call, from ``-inf``) restarts the grid at ``now``
    instead of sending the missed slots back to back: the firmware keeps only the newest packet.
    """

    def __init__(self, period: float, next_t: float = -math.inf) -> None:
        self.period = period
        self.next_t = next_t

    def due(self, now: float) -> bool:
        """Whether a slot is due at ``now``; if so it is taken and the next one scheduled."""
        if now < self.next_t - TIME_EPS:
            return False
        self.next_t += self.period
        if self.next_t <= now:
            self.next_t = now + self.period
        return True
