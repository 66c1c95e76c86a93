"""The flying model judged again on every second flown under it: an axis it stops earning on stops flying.

Beside the fast layer the gate lets a network fly on the axes where it removed part of what the layer leaves on
one second of fresh data. One second is little evidence: on the slow circle a network scored 12 % on z there,
scored about 0 on the seconds that followed, and flew z 12 % worse than the layer alone. With
``online.gate_layer_rejudge`` every later candidate's fresh data (flown under the flying model) also scores the
flying model (``gate.layer_scores``); the sums add up from its swap on. Once ``REJUDGE_ROUNDS`` seconds are in, an
axis whose share of what the layer leaves is too low (``retired_axes``) stops flying: the learner flies the same
networks on the axes left (a new version, so nothing trained on the old one is mixed in), or nominal when none is
left.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace
from typing import Any, Callable

import numpy as np

from cfknode.flight.learning.gate import GateVerdict
from cfknode.models.residual_check import SCORE_KEY

REJUDGE_ROUNDS = 2  # fresh seconds summed before an axis may stop flying: one is the gate's own evidence again

AXES = "xyz"


@dataclass
class _Evidence:
    """The flying model's sums since its swap (``gate.layer_scores``), per axis."""

    version: int
    left: np.ndarray  # what the layer leaves without the model
    with_model: np.ndarray  # ... and with it
    rounds: int = 0

    def share(self) -> np.ndarray:
        return np.where(self.left > 0.0, 1.0 - self.with_model / np.where(self.left > 0.0, self.left, 1.0), 0.0)


def retired_axes(flown: np.ndarray, share: np.ndarray, min_score: float) -> np.ndarray:
    """The flown score (0: an axis not flown) with the axes whose ``share`` since the swap is too low set to 0:
    horizontally not above ``min_score`` (what the gate asked of one second), vertically not positive.

    Vertically the learned term is the inflow, a damping: networks that flew vertical oscillations at 0.3-0.7x the
    layer's MSE scored +1 to +4 % on the seconds after their swap (most of what the layer leaves is the fast force,
    which moves the position little). Horizontally, networks that scored +0 to +1 % there flew 1-3 % worse."""
    return np.where(share > np.array([min_score, min_score, 0.0]), flown, 0.0)


class FlyingRejudge:
    """Mixed into the online learner: ``_rejudge`` after each verdict that scored the flying model."""

    s: Any
    _flying: Any
    _evidence: _Evidence | None = None
    # (t, model, file, queue, event, reason): the learner flies ``model`` (None: nominal) under a new version
    _replace_flying: Callable[[float, Any, Any, tuple[int, ...], str, str], None]

    def _rejudge(self, t: float, verdict: GateVerdict) -> None:
        flying, flown = self._flying, getattr(self._flying.model, "beyond_layer", None)
        if not verdict.flying_sums or flown is None:
            return
        ev = self._evidence
        if ev is None or ev.version != flying.version:
            ev = self._evidence = _Evidence(flying.version, np.zeros(3), np.zeros(3))
        ev.left = ev.left + np.asarray(verdict.flying_sums[0])
        ev.with_model = ev.with_model + np.asarray(verdict.flying_sums[1])
        ev.rounds += 1
        if ev.rounds < REJUDGE_ROUNDS:
            return
        share, min_score = ev.share(), self.s.limits.min_score
        kept = retired_axes(flown, share, min_score)
        gone = [a for a, before, now in zip(AXES, flown, kept) if before > min_score and not now > min_score]
        if not gone:
            return
        reason = (f"stopped earning on {', '.join(gone)} over {ev.rounds} s flown under it (score since its swap "
                  + " / ".join(f"{s:+.1%}" for s in share) + ")")
        if not (kept > min_score).any():
            self._replace_flying(t, None, None, (), "narrow", reason + "; flying nominal")
            return
        model = copy.copy(flying.model)
        model.beyond_layer = kept
        file = replace(flying.file, extra={**flying.file.extra, SCORE_KEY: [float(v) for v in kept]})
        self.recent_models.append((self._next_version, file))  # still this flight's learning: a flight keeps it
        self._replace_flying(t, model, file, flying.queue, "narrow", reason)


__all__ = ["FlyingRejudge", "REJUDGE_ROUNDS", "retired_axes"]
