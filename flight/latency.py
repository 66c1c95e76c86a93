"""Prediction across the command path: plan from where the vehicle will be when the command acts.

A command sent at t reaches the motors' thrust only after the radio hold (up to one
``radio.tx_rate_hz`` period), the firmware's attitude loop and the motor lag: together about
``estimator.command_delay`` seconds. Over [t, t + delay] the vehicle therefore flies the
commands already sent in [t - delay, t), which are known, so the state at t + delay is a
kinematic prediction from the estimate at t (a Smith predictor on the translational model).
"""

from __future__ import annotations

import dataclasses
from collections import deque
from typing import Any

import numpy as np


class CommandDelayPredictor:
    """Keeps the commanded accelerations of the last ``delay`` seconds; ``ahead`` shifts an estimate."""

    def __init__(self, delay: float) -> None:
        if delay < 0.0:
            raise ValueError(f"command delay must be >= 0 s, got {delay}")
        self.delay = delay
        self._sent: deque[tuple[float, np.ndarray]] = deque()

    def reset(self) -> None:
        self._sent.clear()

    def note(self, t: float, acc: np.ndarray) -> None:
        """The command sent at ``t`` (held until the next one)."""
        if self.delay <= 0.0:
            return
        self._sent.append((t, np.array(acc, dtype=float)))
        # Keep the newest command sent at or before t - delay: it is still acting at t.
        while len(self._sent) > 1 and self._sent[1][0] <= t - self.delay:
            self._sent.popleft()

    def ahead(self, est: Any) -> Any:
        """``est`` (with t, p, v) moved to ``est.t + delay`` under the commands in flight."""
        if self.delay <= 0.0 or not self._sent:
            return est
        t = est.t
        p = np.array(est.p, dtype=float)
        v = np.array(est.v, dtype=float)
        start = t - self.delay
        items = list(self._sent)
        for k, (s, acc) in enumerate(items):
            end = items[k + 1][0] if k + 1 < len(items) else t
            a, b = max(s, start), min(end, t)
            h = b - a
            if h <= 0.0:
                continue
            p += v * h + 0.5 * h * h * acc
            v += h * acc
        # Any part of the window before the oldest command kept: no known input, coast.
        gap = items[0][0] - start
        if gap > 0.0:
            p += v * gap
        return dataclasses.replace(est, t=t + self.delay, p=p, v=v)


__all__ = ["CommandDelayPredictor"]
