"""The fast layer's one settings class: the mode and every gain, bound and level it runs with.

Built from the controller config (``controller.adaptation`` + ``controller.adaptation_settings``) by
``settings_from_controller``; the layer's parts each read the fields they need.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

MODES = ("none", "l1", "dob")
Mode = Literal["none", "l1", "dob"]


@dataclass(frozen=True)
class AdaptationSettings:
    """``mode`` and ``controller.adaptation_settings``: each field's unit, bounds and meaning are declared on
    ``cfknode.flight.settings.AdaptationTuning`` (docs/configuration.md); the values come from the config."""

    mode: Mode
    bandwidth_hz: float
    bandwidth_xy_hz: float
    predictor_gain: float
    adaptation_gain: float
    thrust_rate: float
    axis_rate: float
    max_offset: float
    thrust_scale_bounds: tuple[float, float]
    axis_gain_bounds: tuple[float, float]
    stale_pose_s: float
    rebase_window_s: float
    thrust_lag_s: float | None
    thrust_lag_candidates_s: tuple[float, ...]
    step_threshold: float
    step_bandwidth_hz: float
    step_thrust_rate: float
    step_hold_s: float
    oracle_delay_s: float
    output_bandwidth_hz: float
    output_bandwidth_xy_hz: float
    offset_deadband: float
    engage_level: float
    engage_slow_level: float
    engage_slow_s: float
    release_s: float
    step_max_s: float
    wake_radius: float
    accel_cutoff_hz: float
    accel_max_offset: float
    accel_stale_s: float
    model_coefficients: bool
    coefficient_bounds: tuple[float, float]
    coefficient_memory_s: float
    coefficient_prior: float
    model_mean_s: float
    model_min_score: float

    @property
    def enabled(self) -> bool:
        return self.mode != "none"


def settings_from_controller(ctrl: object) -> AdaptationSettings:
    """``AdaptationSettings`` from ``ControllerConfig`` (``adaptation`` + ``adaptation_settings``)."""
    tuning = getattr(ctrl, "adaptation_settings")
    fields = {f: getattr(tuning, f) for f in AdaptationSettings.__dataclass_fields__ if f != "mode"}
    return AdaptationSettings(mode=getattr(ctrl, "adaptation"), **fields)


__all__ = ["AdaptationSettings", "MODES", "Mode", "settings_from_controller"]
