"""A supervised landing that never descends through another drone: glide clear, wait, then descend.

A single drone's supervised landing (landing.py) goes straight down from where the drone is. In
a fleet, a drone below sits on that line (a stack flies one column), so every landing a
supervisor flies for a cause of its own or of the operator's (a stop signal, ``cfknode estop
--land``, mocap loss, the fence, ...) is planned through a ``LandingGate`` the fleet gives it:

1. glide: at the height it is at, to the gate's spot (clear of every drone below it and of
   every spot another drone lands on), a smootherstep that starts and ends at rest;
2. wait: hover there while the gate says a flying drone is below within the separation
   (a stack lands bottom-up: the drone below is down first);
3. descend: the single drone's landing from there. Should a flying drone come under it on
   the way down, it hovers where its descent has got to and waits again.

Before descending the spot is asked again, so a drone that landed under it since (on the
ground, motors off) sends it further on, at most ``MAX_REPLANS`` times; then it lands where it
is (the fleet's separation watch logs it). Only a hard stop (motors off) ignores all this.
"""

from __future__ import annotations

from typing import Protocol, Sequence

import numpy as np

from cfknode.kernel.reference import RefSamples
from cfknode.safety.landing import Landing

MAX_REPLANS = 3
_MOVED_M = 1e-3  # a spot this close to where the drone is: no glide


class LandingGate(Protocol):
    def spot(self, p: np.ndarray) -> tuple[np.ndarray, float]:
        """Where a drone at ``p`` descends (same height) and how long it glides there."""
        ...

    def blocked(self, p: np.ndarray, descending: bool = False) -> bool:
        """Whether a flying drone is below ``p`` within the separation: no descent now (``descending``:
        asked again on the way down, where a gate may ask less than to begin it)."""
        ...


class OrderedLanding:
    """The landing path a supervisor flies (``sample``, ``t_end``), advanced once per tick
    (``advance``); see the module docstring. Mutable: its phase changes as the fleet moves."""

    def __init__(self, gate: LandingGate, start: Sequence[float], ground_z: float, t0: float,
                 land_speed: float) -> None:
        self._gate = gate
        self._ground_z = float(ground_z)
        self._speed = float(land_speed)
        self.start = np.array(start, dtype=float)
        self.replans = 0
        self._descent: Landing | None = None
        self._glide(self.start, float(t0))
        self.first_spot = self._to.copy()

    def _glide(self, here: np.ndarray, now: float) -> None:
        spot, move_s = self._gate.spot(here)
        self._from, self._to = here.copy(), np.array(spot, dtype=float)
        self._to[2] = here[2]
        self._t0 = now
        moved = float(np.linalg.norm(self._to[:2] - self._from[:2])) > _MOVED_M
        self._move_s = max(float(move_s), 1e-3) if moved else 0.0
        self._descent = None

    @property
    def phase(self) -> str:
        return "descend" if self._descent is not None else "glide"

    @property
    def t_end(self) -> float:
        """When the descent reaches the ground; infinite until it has begun."""
        return self._descent.t_end if self._descent is not None else float("inf")

    @property
    def duration(self) -> float:
        return self.t_end - self._t0

    def describe(self) -> str:
        d = float(np.hypot(*(self.first_spot[:2] - self.start[:2])))
        if d <= _MOVED_M:
            return "once no flying drone is below it"
        return (f"after gliding {d:.2f} m to ({self.first_spot[0]:.2f}, {self.first_spot[1]:.2f}) m, clear of "
                "the drones below, once no flying drone is below it")

    def advance(self, now: float) -> None:
        """The tick at ``now``: end the glide, start (or pause) the descent as the gate allows."""
        if self._descent is None:
            if now < self._t0 + self._move_s:
                return  # still gliding
            here = self._to
            if self.replans < MAX_REPLANS:
                spot, _ = self._gate.spot(here)
                if float(np.linalg.norm(np.asarray(spot)[:2] - here[:2])) > _MOVED_M:
                    self.replans += 1  # something came under the spot: further on
                    self._glide(here, now)
                    return
            if not self._gate.blocked(here):
                self._descent = Landing.plan(here, self._ground_z, now, self._speed)
            return
        if self._gate.blocked(self._descent.sample(np.array([now])).p[0], descending=True):
            # A flying drone came under it: hover where the descent has got to, and wait again.
            where = self._descent.sample(np.array([now])).p[0]
            self._from = self._to = where.copy()
            self._t0, self._move_s, self._descent = now, 0.0, None

    def sample(self, t: np.ndarray) -> RefSamples:
        if self._descent is not None:
            return self._descent.sample(t)
        t = np.atleast_1d(np.asarray(t, dtype=float))
        n = t.shape[0]
        p, v, a = np.tile(self._to, (n, 1)), np.zeros((n, 3)), np.zeros((n, 3))
        if self._move_s > 0.0:
            x = np.clip((t - self._t0) / self._move_s, 0.0, 1.0)
            inside = (x > 0.0) & (x < 1.0)
            s = x**3 * (10.0 + x * (6.0 * x - 15.0))
            ds = np.where(inside, 30.0 * x**2 * (1.0 - x) ** 2, 0.0) / self._move_s
            dds = np.where(inside, 60.0 * x * (1.0 - x) * (1.0 - 2.0 * x), 0.0) / self._move_s**2
            d = self._to - self._from
            d[2] = 0.0  # at the height it is at
            p = self._from + s[:, None] * d
            v, a = ds[:, None] * d, dds[:, None] * d
        return RefSamples(t=t, p=p, v=v, a=a, yaw=np.zeros(n))


__all__ = ["LandingGate", "MAX_REPLANS", "OrderedLanding"]
