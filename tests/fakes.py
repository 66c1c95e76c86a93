"""Test doubles shared by several test modules (plain classes; pytest puts tests/ on sys.path)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Est:
    """The part of a state estimate the online side reads."""

    p: np.ndarray
    v: np.ndarray


@dataclass(frozen=True)
class Tick:
    """What the loop hands its observers after a tick (``flight.loop.TickInfo``'s fields the learner reads)."""

    t: float
    est: Est | None
    acc: np.ndarray
    source: str = "mpc"
    model_version: int = 0
    compute_s: float = 0.0


class ListLog:
    """A flight log that keeps messages in memory."""

    def __init__(self) -> None:
        self.messages: list[tuple[str, float, dict[str, Any]]] = []

    def write(self, topic: str, t: float, msg: dict[str, Any]) -> None:
        self.messages.append((topic, t, dict(msg)))

    def topic(self, name: str) -> list[dict[str, Any]]:
        return [m for topic, _, m in self.messages if topic == name]
