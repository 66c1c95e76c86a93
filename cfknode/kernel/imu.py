"""One accelerometer sample from the vehicle, as its log block delivers it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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


__all__ = ["ImuSample"]
