"""Online learning for every drone of a fleet: each its own learner, model slot and trainer process.

A fleet drone learns exactly as a single flight does (cfknode/app/learning.py is the wiring,
reused here): its own ``ModelSlot``, KNODE queue, windows, validation gate and monitor, and its
own trainer process. The trainers are started together and waited for before the fleet's
clock starts, so N torch imports overlap instead of queueing. One process per drone rather
than one shared trainer: measured in docs/fleet.md#measured (on two cores the per-drone
trainers use the core the flight loop leaves idle while it waits for a round).
"""

from __future__ import annotations

import contextlib
from typing import Any, Iterator, Sequence

from cfknode.app.config import Config, ConfigError
from cfknode.app.learning import READY_TIMEOUT_S, online_session, start_trainer
from cfknode.flight.learning.learner import OnlineLearner
from cfknode.flight.learning.trainer_client import TrainerClient
from cfknode.flight.model_slot import ModelSlot


@contextlib.contextmanager
def fleet_trainers(configs: Sequence[Config]) -> Iterator[list[TrainerClient | None]]:
    """One trainer per drone (None where online learning is off), all up before the block; stopped on exit."""
    with contextlib.ExitStack() as stack:
        trainers = [stack.enter_context(start_trainer(c, wait=False)) for c in configs]
        for i, trainer in enumerate(trainers):  # started together: the warm-ups overlap
            if trainer is not None and not trainer.wait_ready(READY_TIMEOUT_S):
                raise ConfigError(f"drone {i + 1}: {trainer.start_problem}")
        yield trainers


@contextlib.contextmanager
def fleet_sessions(
    configs: Sequence[Config], slots: Sequence[ModelSlot | None], logs: Sequence[Any], clocks: Sequence[Any],
    trainers: Sequence[TrainerClient | None], ground_z: Sequence[float],
) -> Iterator[list[OnlineLearner | None]]:
    """Each drone's learner (``online_session``): logging to its own channels, swapping into its own slot."""
    with contextlib.ExitStack() as stack:
        yield [stack.enter_context(online_session(c, slot, log, clock, trainer, ground_z=z))
               for c, slot, log, clock, trainer, z in zip(configs, slots, logs, clocks, trainers, ground_z)]


__all__ = ["fleet_sessions", "fleet_trainers"]
