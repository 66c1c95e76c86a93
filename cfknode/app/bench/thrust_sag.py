"""How far a vehicle must fall after a mass step it cannot lift at once: a lower bound.

At the step the mass jumps, the thrust still holds the old hover and can only follow the
command through a first-order lag. The best any controller can do is command the thrust
clamp at the instant of the step; the acceleration is then g (T/W - 1), with T the lagged
thrust in units of the new weight. The fall stops when the velocity is back to zero:

    T(t) = c - (c - h) exp(-t / tau),   c = T/W at the clamp, h = thrust before the step / new weight

A later command (detection, the command path) only adds to the fall: ``reaction_s`` holds
the old thrust that long first. The robustness bench (cfknode/app/bench/robustness.py) flies
its patterns high enough for the worst of its cells (docs/results.md#bench-robustness).
"""

from __future__ import annotations

import math

G = 9.81  # m/s^2


def lag_sag(thrust_to_weight: float, hover_fraction: float, tau: float, reaction_s: float = 0.0,
            dt: float = 1e-4, g: float = G) -> float:
    """Altitude lost [m] until the fall stops: thrust from ``hover_fraction`` of the new weight
    commanded to ``thrust_to_weight`` ``reaction_s`` after the step, through a lag of ``tau`` s.

    Exact for the lag and the point mass over each ``dt`` (the command held), so ``dt`` only
    samples where the lowest point is.
    """
    if thrust_to_weight <= 1.0:
        raise ValueError(f"thrust-to-weight must be > 1 to stop a fall, got {thrust_to_weight}")
    if hover_fraction < 0.0 or tau < 0.0 or reaction_s < 0.0 or dt <= 0.0:
        raise ValueError("hover fraction, lag, reaction time must be >= 0 and dt > 0")
    if hover_fraction >= 1.0:
        return 0.0  # it never starts to fall
    decay = math.exp(-dt / tau) if tau > 0.0 else 0.0
    thrust, v, z, t = hover_fraction, 0.0, 0.0, 0.0
    lowest = 0.0
    while True:
        command = hover_fraction if t < reaction_s else thrust_to_weight
        gap = thrust - command  # the lagged part, decaying as exp(-s / tau) over the step
        dv = g * ((command - 1.0) * dt + gap * tau * (1.0 - decay))
        z += v * dt + g * ((command - 1.0) * dt * dt / 2.0 + gap * tau * (dt - tau * (1.0 - decay)))
        v += dv
        thrust = command + gap * decay
        t += dt
        lowest = min(lowest, z)
        if v >= 0.0 and t > reaction_s:
            return -lowest


def step_sag(thrust_to_weight: float, factor_before: float, factor_after: float, tau: float,
             reaction_s: float = 0.0) -> float:
    """``lag_sag`` for a mass step from ``factor_before`` to ``factor_after`` (x nominal), the
    thrust hovering the lighter vehicle before it; 0 when the step does not make it heavier."""
    if factor_after <= factor_before:
        return 0.0
    return lag_sag(thrust_to_weight, factor_before / factor_after, tau, reaction_s)


__all__ = ["lag_sag", "step_sag"]
