"""The oracle "adaptation" (``controller.adaptation: oracle``): the same MPC told the true mass at every tick.

A reference row for the benches, not a controller to fly: the thrust scale is the simulator's true
mass over the nominal one, read every tick, and the acceleration offset stays 0. It has the
interface of ``LoopAdaptation`` (``loop.py``), so the thrust cone and the Mellinger
layer see it exactly as they see the adaptive layers; only the estimate differs. Simulation only:
on hardware there is no true mass to read (``mission.py`` refuses it).

``adaptation_settings.oracle_delay_s`` tells it the true mass that much later: a bound for any
estimator that needs that long to see a change (one mocap frame is 10 ms at 100 Hz).
"""

from __future__ import annotations

from collections import deque
from typing import Any, Callable

import numpy as np

from cfknode.flight.adaptation.estimate import AdaptationEstimate
from cfknode.flight.mellinger import CommandShaping, ShapedForce
from cfknode.flight.mpc import ResidualLinearisation
from cfknode.flight.settings import ControllerConfig
from cfknode.kernel.vehicle import VehicleConfig


class OracleAdaptation:
    def __init__(self, ctrl: ControllerConfig, vehicle: VehicleConfig, true_mass: Callable[[], float]) -> None:
        self.ctrl, self.vehicle = ctrl, vehicle
        self._true_mass = true_mass
        self._delay = float(ctrl.adaptation_settings.oracle_delay_s)
        self._heard: deque[tuple[float, float]] = deque()  # (t, true mass) not yet older than the delay
        self._estimate = AdaptationEstimate.neutral()
        self.saturated_ticks = 0

    @property
    def estimate(self) -> AdaptationEstimate:
        return self._estimate

    def f_max(self) -> float:
        """Specific thrust at the clamp [m/s^2] for the true mass."""
        mass = self.vehicle.mass * self._estimate.thrust_scale
        return self.ctrl.max_thrust_fraction * self.vehicle.max_thrust / mass

    def off_air(self) -> None:
        """Nothing to forget: the next tick reads the true mass again."""

    def needs_sample_now(self, now: float, est: Any) -> bool:
        """The oracle reads the true mass on each accelerometer sample's tick before the solve, as the layer it
        stands in for learns a step there."""
        return True

    def before_solve(self, now: float, est: Any, pose_fresh: bool, state: str, model: Any) -> AdaptationEstimate:
        self._heard.append((now, float(self._true_mass())))
        while len(self._heard) > 1 and self._heard[1][0] <= now - self._delay + 1e-9:
            self._heard.popleft()  # the newest sample at least ``delay`` old stays first
        scale = self._heard[0][1] / self.vehicle.mass
        self._estimate = AdaptationEstimate(np.zeros(3), scale, np.ones(3))
        return self._estimate

    def residual(self, model_residual: ResidualLinearisation | None, horizon: int) -> ResidualLinearisation | None:
        """The model's residual unchanged: the oracle's offset is 0."""
        return model_residual

    def shaping(self) -> CommandShaping:
        return CommandShaping(thrust_scale=self._estimate.thrust_scale, axis_gain=(1.0, 1.0))

    def after_command(self, x0: np.ndarray, shaped: ShapedForce, thrust_cmd: int,
                      model_residual: ResidualLinearisation | None) -> None:
        self.saturated_ticks += int(shaped.thrust_saturated or shaped.tilt_saturated)

    def log(self) -> dict[str, Any]:
        return {**self._estimate.to_log(), "f_max": self.f_max(), "mode": "oracle"}

    def summary(self) -> dict[str, Any]:
        return {"adaptation": "oracle", "adaptation_thrust_scale_end": round(self._estimate.thrust_scale, 4),
                "adaptation_saturated_ticks": self.saturated_ticks}


__all__ = ["OracleAdaptation"]
