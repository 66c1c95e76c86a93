"""Reference samples: what a trajectory asks for at a set of times."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Protocol

import numpy as np


@dataclass(frozen=True)
class RefSamples:
    """Reference at times ``t`` (n,): position, velocity, acceleration (n, 3), yaw (n,) rad."""

    t: np.ndarray
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    yaw: np.ndarray


class Reference(Protocol):
    """Anything the controller can track: sampled at any times, with a known span."""

    @property
    def duration(self) -> float: ...

    @property
    def segments(self) -> Mapping[str, tuple[float, float]]: ...

    @property
    def final_position(self) -> np.ndarray: ...

    def sample(self, t: np.ndarray) -> RefSamples: ...
