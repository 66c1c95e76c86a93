"""Another drone's wake is not a heavier vehicle: no mass step is called under it.

A drone passing under another meets its downwash: a downward force a few centimetres wide, crossed in 0.04-0.1 s
at 0.5-1.5 m/s. To the step detectors (step_detect.py, imu_step.py) its onset is a vehicle that became heavier,
and the step's fit (step_fit.py), a lasting change fitted to the few frames after it, put the thrust scale at
its bound (2.5) for a moment while the commands scaled with it: 0.2 m along the line at 1.5 m/s
(docs/history.md#another-drones-wake-is-not-a-mass-step). A wake only ever pushes down, so while the drone
passes under another within ``radius`` horizontally (their horizontal distance changing faster than
``PASS_SPEED``, and not since below ``STOP_SPEED``), and for ``HOLD_S`` after it has left, no step that makes
the vehicle heavier is called. A lighter one (leaving a wake) still is, and so is a heavier one while the drone
is under another and not passing: one that flies into a wake and stops there, or flies stacked under another,
carries that force for seconds, as it would a payload.

Nor is it the motors' lag: the layer's lag bank (thrust_lag.py) took a wake's push, met with more thrust, for the
longest lag (150 ms against the vehicle's 15 ms) once the accelerometer fed it. So no lag is learned while the drone
is under another within ``radius`` and the reach (passing or not: ``reaches``), nor for ``LAG_HOLD_S`` after a pass,
nor from the fit of a step begun then, however late it ends (``LoopAdaptation``, flight/adaptation/loop.py).
"""

from __future__ import annotations

import math

import numpy as np

from cfknode.flight.neighbours import NONE_ABOVE

HOLD_S = 0.3  # s after leaving the wake's reach: the detectors' run still holds the wake's surprise
# s after leaving it that no motor lag is learned: the layer's answer to the wake still moves the accelerometer's
# samples (at a 1 m/s crossing's turn, 0.1 s after HOLD_S, they chose 150 ms against the vehicle's 15).
LAG_HOLD_S = 0.6
# m/s of horizontal relative speed a pass starts above: a fleet's take-off moves a drone into place under another at
# 0.35-0.40 m/s and stays (a step refused there came 0.13 s late); a 0.5 m/s crossing measures 0.42-0.47 under the jet.
PASS_SPEED = 0.45
STOP_SPEED = 0.2  # m/s a pass ends below while under the wake (stopped there: its wake lasts, as a payload does)
SPEED_SPAN_S = 0.05  # s the relative speed is measured over (1 mm of mocap noise: 0.02 m/s)
REACH_M = float(NONE_ABOVE[2])  # m: no wake beyond this gap (the neighbour input's "none above")


class WakeGuard:
    """``update`` each tick with the drone's position and the drone above's: whether a heavier step is refused."""

    def __init__(self, radius: float) -> None:
        self.radius = radius
        self.reset()

    def reset(self) -> None:
        self._under_t = -math.inf  # s, the last tick passing under another drone's wake
        self._mark: tuple[float, float, float] | None = None  # (t, dx, dy) the relative speed is measured from
        self.speed = 0.0  # m/s, the horizontal relative speed last measured
        self._passing = False  # under the wake since the speed was above PASS_SPEED, and not below STOP_SPEED since

    def update(self, t: float, p: np.ndarray | None, above: np.ndarray | None) -> bool:
        """True while ``p`` passes under ``above`` (world positions) or did within ``HOLD_S``; False with either
        unknown."""
        if self.radius > 0.0 and p is not None and above is not None:
            dx, dy = float(above[0]) - float(p[0]), float(above[1]) - float(p[1])
            self._measure(t, dx, dy)
            under = self.reaches(p, above)
            # Two thresholds: a slow pass's measured speed dips around PASS_SPEED, and one dip ended the hold.
            self._passing = under and self.speed > (STOP_SPEED if self._passing else PASS_SPEED)
            if self._passing:
                self._under_t = t
            elif under:  # arrived (or stopped) under it: the wake lasts, as a payload does
                self._under_t = -math.inf
        return self.held(t)

    def held(self, t: float, hold: float = HOLD_S) -> bool:
        """Whether a pass under a wake was seen within ``hold`` of ``t`` (as ``update`` last found)."""
        return t - self._under_t < hold

    def reaches(self, p: np.ndarray | None, above: np.ndarray | None) -> bool:
        """Whether ``p`` is under ``above`` within the wake's reach, passing or not (False with either unknown, or the
        guard off): where the motors' lag is not learned either, whose evidence a wake's push would fake."""
        if self.radius <= 0.0 or p is None or above is None:
            return False
        dx, dy, dz = (float(above[k]) - float(p[k]) for k in range(3))
        return 0.0 < dz < REACH_M and math.hypot(dx, dy) < self.radius

    def _measure(self, t: float, dx: float, dy: float) -> None:
        """The horizontal relative speed over the last ``SPEED_SPAN_S``."""
        if self._mark is None or t < self._mark[0]:
            self._mark = (t, dx, dy)
        elif t - self._mark[0] >= SPEED_SPAN_S:
            t0, x0, y0 = self._mark
            self.speed = math.hypot(dx - x0, dy - y0) / (t - t0)
            self._mark = (t, dx, dy)


__all__ = ["HOLD_S", "LAG_HOLD_S", "PASS_SPEED", "REACH_M", "STOP_SPEED", "WakeGuard"]
