"""The fast adaptation layer: what the flying model still gets wrong, estimated every tick (see ``layer.py``).

Its parts, one job each:
- ``settings``: the one settings class; ``estimate``: what the layer tells the controller, its state included;
- ``observer``: the estimator as pure functions; ``engagement``: the axes it acts on;
- ``step_detect``: a mass step in the mocap frames, and how long it is tracked; ``step_fit``: the step's mass
  fitted to the heights; ``imu_step``: a step in the accelerometer; ``thrust_lag``: the motors' lag;
- ``layer``: ``FastAdaptation``, the estimator's state; ``loop``: ``LoopAdaptation``, the layer in the flight
  loop; ``oracle``: the true mass, a bench reference;
- ``protocol``: the controller's adaptation slot (``AdaptationLayer``) and a layer that adapts nothing.
"""

from cfknode.flight.adaptation.engagement import engagement
from cfknode.flight.adaptation.estimate import AdaptationEstimate, applied_estimate
from cfknode.flight.adaptation.imu_step import ImuStepDetector
from cfknode.flight.adaptation.layer import FastAdaptation
from cfknode.flight.adaptation.loop import GROUND_MARGIN, LoopAdaptation, body_z
from cfknode.flight.adaptation.observer import (
    axis_transfer, dob_step, l1_step, rebase_offset, shrink, sigma_after_transfer, smooth_step, thrust_transfer,
)
from cfknode.flight.adaptation.oracle import OracleAdaptation
from cfknode.flight.adaptation.protocol import AdaptationLayer, NoAdaptation
from cfknode.flight.adaptation.settings import MODES, AdaptationSettings, settings_from_controller
from cfknode.flight.adaptation.step_detect import FrameStepDetector, StepTracker, cusum_step
from cfknode.flight.adaptation.step_fit import StepEstimate, StepFit
from cfknode.flight.adaptation.thrust_lag import ThrustLagBank

__all__ = [
    "AdaptationEstimate", "AdaptationLayer", "AdaptationSettings", "FastAdaptation", "FrameStepDetector",
    "GROUND_MARGIN", "ImuStepDetector", "LoopAdaptation", "MODES", "NoAdaptation", "OracleAdaptation",
    "StepEstimate", "StepFit", "StepTracker", "ThrustLagBank", "applied_estimate", "axis_transfer", "body_z",
    "cusum_step", "dob_step", "engagement", "l1_step", "rebase_offset", "settings_from_controller", "shrink",
    "sigma_after_transfer", "smooth_step", "thrust_transfer",
]
