"""A tick observer that swaps a model into a model slot at a flight time, as an online learner's swap lands between
ticks: an injected NaN model (``faults.nan_model_at``) and an air model that arrives late (``sim.air_model_from_s``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

_TIME_EPS = 1e-9  # s: a tick scheduled at ``t`` counts as reaching it


@dataclass
class SwapAt:
    """Swaps ``model`` into ``slot`` (a ``ModelSlot``) on the first tick at or after flight time ``t``, once."""

    slot: Any
    model: Any
    t: float
    done: bool = False

    def on_tick(self, tick: Any) -> None:
        if not self.done and tick.t >= self.t - _TIME_EPS:
            self.done = True
            self.slot.swap(self.model, self.slot.version + 1, tick.t)


__all__ = ["SwapAt"]
