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


def sample_twice(reference: Reference, times: np.ndarray,
                 later: np.ndarray | None) -> tuple[RefSamples, RefSamples | None]:
    """``reference`` at ``times`` and at ``later`` (None: not needed) in one call: a sample's cost is mostly per
    call, and a plan from a state predicted ahead needs the reference over both (flight/latency.py)."""
    if later is None:
        return reference.sample(times), None
    both = reference.sample(np.concatenate((times, later)))
    n = len(times)
    first = RefSamples(both.t[:n], both.p[:n], both.v[:n], both.a[:n], both.yaw[:n])
    return first, RefSamples(both.t[n:], both.p[n:], both.v[n:], both.a[n:], both.yaw[n:])
