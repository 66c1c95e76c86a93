"""One accelerometer sample from the vehicle, as its log block delivers it, and where the loop gets it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

# The firmware logs acc.x/y/z in g of 9.81 m/s^2 (its GRAVITY_MAGNITUDE); the simulated firmware uses the same.
FIRMWARE_G = 9.81


@dataclass(frozen=True)
class ImuSample:
    """``t``: when the vehicle measured it (flight clock, s); ``specific_force``: what the accelerometer reads,
    in the body frame, m/s^2 (the firmware logs g; at hover it is about (0, 0, +9.81))."""

    t: float
    specific_force: np.ndarray

    def __post_init__(self) -> None:
        f = np.array(self.specific_force, dtype=np.float64)
        if f.shape != (3,):
            raise ValueError(f"ImuSample needs specific_force (3,), got {f.shape}")
        f.flags.writeable = False  # shared by the controller and the log
        object.__setattr__(self, "t", float(self.t))
        object.__setattr__(self, "specific_force", f)


class ImuSource(Protocol):
    """What the flight loop reads each tick: the newest sample measured at or before ``now``, or None."""

    def latest(self, now: float) -> ImuSample | None: ...


__all__ = ["FIRMWARE_G", "ImuSample", "ImuSource"]
