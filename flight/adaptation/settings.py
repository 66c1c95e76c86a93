"""The fast layer's one settings class: the mode and every gain, bound and level it runs with.

Built from the controller config (``controller.adaptation`` + ``controller.adaptation_settings``) by
``settings_from_controller``; the layer's parts each read the fields they need.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

MODES = ("none", "l1", "dob")
Mode = Literal["none", "l1", "dob"]


@dataclass(frozen=True)
class AdaptationSettings:
    mode: Mode
    bandwidth_hz: float  # low-pass cut-off of the vertical disturbance estimate (dob) / of the l1 output filter
    bandwidth_xy_hz: float  # the same for x and y: lower, since mocap noise enters there as tilt jitter
    predictor_gain: float  # 1/s, l1: velocity predictor's error feedback
    adaptation_gain: float  # 1/s^2, l1: adaptive law gain (the fast inner estimate)
    thrust_rate: float  # 1/s: how fast the vertical error moves into thrust_scale
    axis_rate: float  # 1/s: how fast horizontal command-proportional error moves into axis_gain
    max_offset: float  # m/s^2 per axis
    thrust_scale_bounds: tuple[float, float]
    axis_gain_bounds: tuple[float, float]
    stale_pose_s: float  # s without a fresh mocap pose: frozen
    rebase_window_s: float  # s of recent ticks the re-base at a model swap averages over
    thrust_lag_s: float | None = None  # s, first-order lag from the thrust sent to the thrust acting (None: chosen)
    thrust_lag_candidates_s: tuple[float, ...] = (0.015, 0.04, 0.08, 0.15)  # s, the lags chosen among when None
    step_threshold: float = 0.0  # alarm level of the vertical step detector (CUSUM of noise-normalised surprise); 0 off
    step_bandwidth_hz: float = 10.0  # vertical cut-off while a detected step is being tracked
    step_thrust_rate: float = 400.0  # 1/s, thrust_rate while a detected step is being tracked
    step_hold_s: float = 0.3  # s after an alarm at the step bandwidth and rate
    oracle_delay_s: float = 0.0  # s, the oracle reference only (oracle.py)
    output_bandwidth_hz: float = 0.0  # dob: the vertical offset is sigma low-passed again at this cut-off; 0 sigma itself
    output_bandwidth_xy_hz: float = 0.0  # the same for x and y
    offset_deadband: float = 0.0  # m/s^2: a horizontal offset well below it is shrunk toward 0 (see shrink); 0 off
    engage_level: float = 0.0  # m/s^2: an axis acts once its evidence is above this (see engagement); 0: always
    engage_slow_level: float = math.inf  # m/s^2: ... or once the evidence's slow mean is above this
    engage_slow_s: float = 2.0  # s, time constant of that mean
    release_s: float = 1.0  # s with both under half their levels before an axis lets go again
    step_max_s: float = 1.0  # s a step is tracked at most after its first alarm; later alarms re-arm, never extend it

    @property
    def enabled(self) -> bool:
        return self.mode != "none"


def settings_from_controller(ctrl: object) -> AdaptationSettings:
    """``AdaptationSettings`` from ``ControllerConfig`` (``adaptation`` + ``adaptation_settings``)."""
    tuning = getattr(ctrl, "adaptation_settings")
    fields = {f: getattr(tuning, f) for f in AdaptationSettings.__dataclass_fields__ if f != "mode"}
    return AdaptationSettings(mode=getattr(ctrl, "adaptation"), **fields)


__all__ = ["AdaptationSettings", "MODES", "Mode", "settings_from_controller"]
