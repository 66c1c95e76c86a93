"""The flight stack's radio: ``CflibRadio`` (cflib_radio.py) behind latest-value slots, and
``HardwareRadio`` (hardware_radio.py) with what a real Crazyflie needs. Imported from here."""

from __future__ import annotations

from cfknode.app.backends.cflib_radio import (
    SUPERVISOR_PROTOCOL,
    CflibRadio,
    LinkSafety,
    RadioError,
    RadioStats,
    ensure_cflib_drivers,
)
from cfknode.app.backends.hardware_radio import (
    CONTROLLER_PID,
    ESTIMATOR_KALMAN,
    TELEMETRY_VARIABLES,
    HardwareRadio,
    LinkStatistics,
    Telemetry,
)

__all__ = [
    "CONTROLLER_PID",
    "ESTIMATOR_KALMAN",
    "SUPERVISOR_PROTOCOL",
    "TELEMETRY_VARIABLES",
    "CflibRadio",
    "HardwareRadio",
    "LinkSafety",
    "LinkStatistics",
    "RadioError",
    "RadioStats",
    "Telemetry",
    "ensure_cflib_drivers",
]
