"""The controller's adaptation slot: what it asks of a layer each tick, and a layer that adapts nothing.

``Controller`` calls, per tick: ``before_solve`` (read the state, update the estimate) -> ``f_max`` (the
thrust cone's bound) -> ``residual`` (the MPC's residual with the layer's part added) -> ``shaping`` (what
the Mellinger layer flies with) -> ``after_command`` (what was flown). With ``prepares_after_send`` the
update and the record wait for ``Controller.prepare`` after the send, unless ``needs_sample_now`` says a new
accelerometer sample must be learned before the solve. ``LoopAdaptation`` (the observer,
``loop.py``) and ``OracleAdaptation`` (the true mass, ``oracle.py``) fill it; ``NoAdaptation`` flies the
model alone through the same path, for an embedder who wants the layer's interface without its estimate.
With a model flying, ``LoopAdaptation`` also weights the model's residual per axis (``composite.py``): that
part enters through ``residual`` too, as the model's linearisation scaled per row.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

from cfknode.flight.adaptation.estimate import AdaptationEstimate
from cfknode.flight.mellinger import CommandShaping, ShapedForce
from cfknode.flight.mpc_problem import ResidualLinearisation
from cfknode.flight.settings import ControllerConfig
from cfknode.kernel.vehicle import VehicleConfig


@runtime_checkable
class AdaptationLayer(Protocol):
    """What ``Controller`` asks of its adaptation slot each tick."""

    @property
    def estimate(self) -> AdaptationEstimate: ...

    def before_solve(self, now: float, est: Any, pose_fresh: bool, state: str, model: Any) -> AdaptationEstimate: ...

    def needs_sample_now(self, now: float, est: Any) -> bool: ...

    def f_max(self) -> float: ...

    def residual(self, model_residual: ResidualLinearisation | None,
                 horizon: int) -> ResidualLinearisation | None: ...

    def shaping(self) -> CommandShaping: ...

    def after_command(self, x0: np.ndarray, shaped: ShapedForce, thrust_cmd: int,
                      model_residual: ResidualLinearisation | None) -> None: ...

    def off_air(self) -> None: ...

    def log(self) -> dict[str, Any]: ...

    def summary(self) -> dict[str, Any]: ...


class NoAdaptation:
    """The model alone, through the layer's path: offset 0, nominal mass, unit axis gains, the nominal cone."""

    def __init__(self, ctrl: ControllerConfig, vehicle: VehicleConfig) -> None:
        self._f_max = ctrl.max_thrust_fraction * vehicle.max_thrust / vehicle.mass
        self._estimate = AdaptationEstimate.neutral()
        self.saturated_ticks = 0

    @property
    def estimate(self) -> AdaptationEstimate:
        return self._estimate

    def before_solve(self, now: float, est: Any, pose_fresh: bool, state: str, model: Any) -> AdaptationEstimate:
        return self._estimate

    def needs_sample_now(self, now: float, est: Any) -> bool:
        """Nothing learned: no sample is needed before the solve."""
        return False

    def f_max(self) -> float:
        """Specific thrust at the clamp [m/s^2] for the nominal mass."""
        return self._f_max

    def residual(self, model_residual: ResidualLinearisation | None,
                 horizon: int) -> ResidualLinearisation | None:
        return model_residual

    def shaping(self) -> CommandShaping:
        return CommandShaping(thrust_scale=1.0, axis_gain=(1.0, 1.0))

    def after_command(self, x0: np.ndarray, shaped: ShapedForce, thrust_cmd: int,
                      model_residual: ResidualLinearisation | None) -> None:
        self.saturated_ticks += int(shaped.thrust_saturated or shaped.tilt_saturated)

    def off_air(self) -> None:
        """Nothing to forget."""

    def log(self) -> dict[str, Any]:
        return {**self._estimate.to_log(), "f_max": self._f_max, "mode": "none"}

    def summary(self) -> dict[str, Any]:
        return {"adaptation": "none", "adaptation_saturated_ticks": self.saturated_ticks}


__all__ = ["AdaptationLayer", "NoAdaptation"]
