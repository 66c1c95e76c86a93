"""Which axes the fast layer acts on: where the model's error is clearly more than noise.

See the package docstring (``layer.py``) for why an axis that does not act flies the model alone.
"""

from __future__ import annotations

import numpy as np


def engage_axis(engaged: bool, quiet: float, evidence: float, slow: float, level: float, slow_level: float,
                release_s: float, dt: float) -> tuple[bool, float]:
    """One axis: (acts, seconds its evidence has been quiet); see ``engagement``. Plain floats: the layer calls
    it three times a tick, where numpy's per-call cost on 3-vectors was most of the work."""
    if level <= 0.0:
        return True, 0.0
    size, mean = abs(evidence), abs(slow)
    quiet = quiet + dt if size < 0.5 * level and mean < 0.5 * slow_level else 0.0
    return (engaged or size > level or mean > slow_level) and quiet < release_s, quiet


def engagement(engaged: np.ndarray, quiet: np.ndarray, evidence: np.ndarray, slow: np.ndarray, level: float,
               slow_level: float, release_s: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Per axis (x, y, vertical): (acts, seconds its evidence has been quiet).

    An axis acts once its evidence (m/s^2 the model gets wrong there) is above ``level``, or the evidence's
    slow mean ``slow`` above ``slow_level`` (a small error that persists), and lets go after ``release_s`` with
    both under half their levels; ``level`` 0: every axis always acts. On a plant the model matches, the
    estimate is the velocity's noise and unmodelled dynamics that no constant cancels: acting on it cost
    plain MPC 0.1-6 % on quiet plants."""
    axes = [engage_axis(bool(engaged[i]), float(quiet[i]), float(evidence[i]), float(slow[i]), level, slow_level,
                        release_s, dt) for i in range(3)]
    return np.array([a for a, _ in axes], dtype=bool), np.array([q for _, q in axes])


class Engagement:
    """The engagement's state over ticks: per axis whether it acts, its quiet time and its evidence's slow mean."""

    def __init__(self, level: float, slow_level: float, slow_s: float, release_s: float) -> None:
        self.level, self.slow_level, self.slow_s, self.release_s = level, slow_level, slow_s, release_s
        self.reset()

    def reset(self) -> None:
        on = self.level <= 0.0  # level 0: every axis always acts
        self.acts: tuple[bool, bool, bool] = (on, on, on)
        self._quiet = [0.0, 0.0, 0.0]
        self._slow = [0.0, 0.0, 0.0]  # the evidence's slow mean

    def update(self, evidence: tuple[float, float, float], dt: float) -> tuple[bool, bool, bool]:
        """The axes that act after this tick's ``evidence`` (m/s^2 per axis)."""
        k = min(1.0, dt / self.slow_s)
        acts = []
        for i in range(3):
            slow = self._slow[i] = self._slow[i] + k * (evidence[i] - self._slow[i])
            on, self._quiet[i] = engage_axis(self.acts[i], self._quiet[i], evidence[i], slow, self.level,
                                             self.slow_level, self.release_s, dt)
            acts.append(on)
        self.acts = (acts[0], acts[1], acts[2])
        return self.acts


__all__ = ["Engagement", "engage_axis", "engagement"]
