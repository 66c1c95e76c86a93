"""Online learning for every drone of a fleet: each its own learner, model slot and trainer queue.

A fleet drone learns exactly as a single flight does (cfknode/app/learning.py is the wiring,
reused here): its own ``ModelSlot``, KNODE queue, windows, validation gate and monitor. Their
rounds go to a shared trainer process (``SharedTrainer``), in the order they are sent, one process for
the drones whose rounds train alike: on two cores one trainer per drone was slower, because N trainers
training at once take the CPU from the fleet's flight loop, the critical path (docs/fleet.md#measured).
Rounds are seeded by their own round number, so a drone's models are the ones a trainer of its own would give.
"""

from __future__ import annotations

import contextlib
from typing import Any, Iterator, Sequence

from cfknode.app.config import Config, ConfigError
from cfknode.app.learning import check_online, online_session, trainer_settings
from cfknode.flight.learning.learner import OnlineLearner
from cfknode.flight.learning.shared_trainer import SharedTrainer, TrainerPort
from cfknode.flight.model_slot import ModelSlot
from cfknode.models.trainer_process import TrainerSettings


@contextlib.contextmanager
def fleet_trainers(configs: Sequence[Config]) -> Iterator[list[TrainerPort | None]]:
    """Each drone's port on a shared trainer (None for all when online learning is off); up before the block.

    Drones whose rounds train alike share one process; a fleet whose lower drones learn the drone above alone
    (``fleet.wake_only``, chosen per drone by ``fleet.wake_below``) has two: a wake network's inputs differ."""
    for c in configs:
        check_online(c)
    if not configs or not configs[0].online.enabled:
        yield [None] * len(configs)
        return
    groups: dict[TrainerSettings, list[int]] = {}
    for i, c in enumerate(configs):
        groups.setdefault(trainer_settings(c), []).append(i)
    start_timeout = configs[0].online.trainer_start_timeout
    shared = [SharedTrainer(settings, configs[0].online.trainer_timeout, len(members), start_timeout=start_timeout)
              for settings, members in groups.items()]
    try:
        for trainer in shared:
            trainer.start()
        for trainer in shared:
            if not trainer.wait_ready(start_timeout):
                raise ConfigError(trainer.client.start_problem)
        ports: list[TrainerPort | None] = [None] * len(configs)
        for trainer, members in zip(shared, groups.values()):
            for port, i in zip(trainer.ports, members):
                ports[i] = port
        yield ports
    finally:
        for trainer in shared:
            trainer.close()


@contextlib.contextmanager
def fleet_sessions(
    configs: Sequence[Config], slots: Sequence[ModelSlot | None], logs: Sequence[Any], clocks: Sequence[Any],
    trainers: Sequence[TrainerPort | None], ground_z: Sequence[float],
) -> Iterator[list[OnlineLearner | None]]:
    """Each drone's learner (``online_session``): logging to its own channels, swapping into its own slot."""
    with contextlib.ExitStack() as stack:
        yield [stack.enter_context(online_session(c, slot, log, clock, trainer, ground_z=z))  # type: ignore[arg-type]
               for c, slot, log, clock, trainer, z in zip(configs, slots, logs, clocks, trainers, ground_z)]


__all__ = ["fleet_sessions", "fleet_trainers"]
