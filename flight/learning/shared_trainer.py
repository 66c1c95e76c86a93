"""One trainer process serving several learners (a fleet's drones): a queue of rounds, one port per learner.

Each learner talks to its ``TrainerPort`` exactly as to its own ``TrainerClient`` (states
``starting``, ``idle``, ``busy``, ``stopped``; ``submit``, ``poll``, ``start``). The ports share
one child process that trains the rounds in the order they were sent, each tagged with its
port's index, so results go back to the learner that asked. Rounds are independent (each is
seeded by its own round number), so a learner gets the same models as from a trainer of its own.

Why shared: on two cores the flight loop of the whole fleet is the critical path, and N trainers
training at once take the CPU from it; one trainer takes at most one core (docs/fleet.md#measured).

Faults: a crash or a hang (no result within ``timeout`` of the round at the head of the queue
starting) is the fault of every port with a round in the queue (those rounds are lost); their
learners count it and restart the process as after their own trainer's fault. A port that lost
nothing finds the process starting, or starts it itself when it next polls.
"""

from __future__ import annotations

import math
import time
from collections import deque
from typing import Any, Callable

from cfknode.flight.learning.trainer_client import TrainerClient, TrainerFault
from cfknode.models.trainer_process import TrainerReady, TrainerSettings, TrainOutcome, TrainRequest


class _QueueClient(TrainerClient):
    """A ``TrainerClient`` on the tagged protocol whose requests may queue: ``busy`` while any round is out."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.tagged = True

    def submit(self, request: Any) -> None:
        if self.state == "idle":
            super().submit(request)  # the head of the queue: its hang deadline counts from now
        elif self.state == "busy":
            self._send(request)
        else:
            raise RuntimeError(f"trainer is {self.state}, not idle")


class SharedTrainer:
    """The process and its queue; ``ports[i]`` is learner i's client."""

    def __init__(self, settings: TrainerSettings, timeout: float, n: int, start_timeout: float = 120.0,
                 wall: Callable[[], float] = time.perf_counter) -> None:
        self.client = _QueueClient(settings, timeout, start_timeout, wall)
        self._wall = wall
        self._queue: deque[int] = deque()  # tags of the rounds sent and not answered, oldest first
        self._inbox: list[deque[Any]] = [deque() for _ in range(n)]
        self.ports = [TrainerPort(self, i) for i in range(n)]

    def start(self) -> None:
        """Start the process unless another port has already (re)started it."""
        if self.client.state == "stopped":
            self._queue.clear()
            self.client.start()

    def wait_ready(self, timeout: float) -> bool:
        ok = self.client.wait_ready(timeout)  # pre-flight: the ready note is consumed here, as for one client
        return ok

    def send(self, tag: int, request: TrainRequest) -> None:
        self.client.submit((tag, request))
        self._queue.append(tag)

    def pump(self, timeout: float) -> bool:
        """Take the process's next message (waiting up to ``timeout``) into its port's inbox; True if one came."""
        message = self.client.poll(timeout)
        if message is None:
            return False
        if isinstance(message, tuple):
            tag, outcome = message
            if self._queue and self._queue[0] == tag:
                self._queue.popleft()
            self._inbox[tag].append(outcome)
            if self._queue:
                self.client.sent_wall = self._wall()  # the next round starts now: its hang deadline too
            else:
                self.client.state = "idle"
        elif isinstance(message, TrainerFault):
            for tag in set(self._queue):  # their rounds are lost
                self._inbox[tag].append(message)
            self._queue.clear()
        else:  # ready after a restart: every port's news
            for inbox in self._inbox:
                inbox.append(message)
        return True

    def close(self) -> None:
        self.client.close()


class TrainerPort:
    """One learner's view of the ``SharedTrainer``: the interface of ``TrainerClient``."""

    def __init__(self, shared: SharedTrainer, tag: int) -> None:
        self._shared = shared
        self.tag = tag
        self._out = False  # a round of ours not yet handed to the learner
        self.sent_wall = math.nan
        self.start_problem = ""

    @property
    def timeout(self) -> float:
        return self._shared.client.timeout

    @property
    def start_wall(self) -> float:
        return self._shared.client.start_wall

    @property
    def pid(self) -> int | None:
        return self._shared.client.pid

    @property
    def warmup_s(self) -> float:
        return self._shared.client.warmup_s

    @property
    def state(self) -> str:
        if self._out:
            return "busy"  # until its result (or the fault that lost it) is read
        shared = self._shared.client.state
        # Stopped by a fault another port's learner did not restart: this port restarts it on its next poll.
        return "starting" if shared in ("starting", "stopped") else "idle"

    @property
    def busy(self) -> bool:
        return self.state == "busy"

    def start(self) -> None:
        self._shared.start()
        self._out = False

    def wait_ready(self, timeout: float) -> bool:
        ok = self._shared.wait_ready(timeout)
        self.start_problem = self._shared.client.start_problem
        return ok

    def submit(self, request: TrainRequest) -> None:
        if self.state != "idle":
            raise RuntimeError(f"trainer is {self.state}, not idle")
        self.sent_wall = self._shared.client._wall()
        self._shared.send(self.tag, request)
        self._out = True

    def poll(self, timeout: float = 0.0) -> TrainOutcome | TrainerReady | TrainerFault | None:
        """This learner's next message (its result, a ready note, a fault); waits up to ``timeout`` s."""
        wall = self._shared.client._wall
        deadline = wall() + timeout
        inbox = self._shared._inbox[self.tag]
        while True:
            if inbox:
                message = inbox.popleft()
                if isinstance(message, (TrainOutcome, TrainerFault)):
                    self._out = False
                return message
            left = deadline - wall()
            if self._shared.client.state == "stopped":
                self._shared.start()
            if not self._shared.pump(max(0.0, left)) and left <= 0.0:
                return None

    def kill(self) -> None:
        self._shared.client.kill()

    def close(self, timeout: float = 2.0) -> None:
        """The process is the ``SharedTrainer``'s: it is stopped once, by its owner."""


__all__ = ["SharedTrainer", "TrainerPort"]
