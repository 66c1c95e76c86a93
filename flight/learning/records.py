"""What the learner is told (its settings) and what it keeps: rounds, swaps, counters, and its inner states."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Generator, Protocol


from cfknode.flight.learning.monitor import MonitorSettings
from cfknode.flight.learning.windows import MIN_HEIGHT, WakeOnly
from cfknode.flight.learning.gate import GateLimits, GateVerdict
from cfknode.flight.learning.latency import LatencyPolicy
from cfknode.models.modelfile import ModelFile
from cfknode.models.residual_np import ResidualQueue
from cfknode.models.trainer_process import TrainOutcome, TrainRequest, Window


class Log(Protocol):
    def write(self, topic: str, t: float, msg: dict[str, Any]) -> None: ...


# Supervisor states in which the flight is ending (landing, landed, stopped or refused).
_ENDING_STATES = frozenset({"LAND", "LANDED", "EMERGENCY", "IDLE"})


@dataclass(frozen=True)
class LearnerSettings:
    t_col: float
    period: float  # s between ticks
    lockstep: bool  # flight clock is the simulator's (pace honest latency)
    paper_lockstep: bool
    gate: bool
    gate_min_pairs: int
    replay_windows: int
    start_time: float
    rollback_ticks: int
    rollback_fallbacks: int
    max_restarts: int
    limits: GateLimits
    filter_hz: float  # training.velocity_filter_hz
    holdout_fraction: float  # training.validation_fraction: the tail the paper-lockstep gate judges on
    queue_size: int  # knode.queue_size
    monitor: MonitorSettings | None = None  # drop a flying model the world changed under (None: never)
    ground_z: float | None = None  # the floor's height: ticks near it are not learned from (None: no floor)
    min_height: float = MIN_HEIGHT  # m: "near" the floor, for ground_z (online.min_height)
    latency: LatencyPolicy = LatencyPolicy()  # lockstep only: the delay a model is applied with (online_latency.py)
    # The gate's limits for fresh data the fast layer measured nothing on (held near the floor): there it supplied
    # no constant, so a candidate is judged with its constants, as without a layer (None: ``limits`` always).
    held_limits: GateLimits | None = None
    # The networks see the neighbour alone (fleet.wake_only; windows.WakeOnly: how its recorder reads the thrust
    # sent). None: they see the drone's own state too.
    wake_only: WakeOnly | None = None
    command_lag_s: tuple[float, float] = (0.0, 0.0)  # (x/y, z) s: the lags the recorded commands act through


@dataclass(frozen=True)
class RoundRecord:
    """One training round as the flight saw it."""

    round: int
    version: int
    window: tuple[float, float]
    sent_t: float  # flight time the request was sent
    latency_s: float  # s from send to the earliest swap: the wall round trip, or the latency policy's delay
    train_wall_s: float  # the trainer's own wall time for the round
    train_cpu_s: float
    loss: float
    outcome: str  # "swap" | "reject" | "failed" | "lost" (crash/hang/unfinished)
    reason: str = ""
    applied_t: float = math.nan  # flight time of the swap (the next tick flies it)
    received_t: float = math.nan  # flight time the result arrived
    rmse_candidate: float = math.nan
    rmse_current: float = math.nan


@dataclass(frozen=True)
class SwapEvent:
    t: float  # on_tick time of the swap; ticks after t fly the new model
    version: int
    swap_s: float  # the slot write (a reference assignment)
    install_s: float  # fold the file into numpy stacks + gate + swap, spread over tick gaps
    max_slice_s: float  # the longest of those slices: what one tick gap had to absorb
    kind: str  # "swap" | "rollback" | "drop" | "narrow"


@dataclass
class _Outstanding:
    request: TrainRequest
    sent_t: float
    sent_wall: float


@dataclass(frozen=True)
class _PaceFrom:
    """While the trainer works (a round or a restart), flight time may not outrun the wall time since this point."""

    t: float
    wall: float


@dataclass
class _Held:
    outcome: TrainOutcome
    window: Window  # the window it trained on
    received_t: float
    sent_t: float
    latency_s: float  # observed wall round trip
    apply_at: float  # earliest flight time the next tick may fly it


@dataclass
class _Gating:
    """A candidate going through the gate, one slice per tick gap."""

    held: _Held
    candidate: ResidualQueue | None  # set when the gate is done
    steps: Generator[None, None, tuple[GateVerdict, ResidualQueue]]
    work_s: float  # wall time of the slices so far (fold and filtering included)
    max_slice_s: float
    job: int = 0  # the trainer judges it (``install.gate_job``): the job's id (0: the slices run here)
    calls: int = 0  # tick gaps since the job was sent
    verdict: tuple[GateVerdict, int] | None = None  # the job's answer: the verdict and its slice count


@dataclass
class _Flying:
    """The model in the slot, with what rollback and the next round need."""

    model: Any | None
    version: int
    file: ModelFile | None
    queue: tuple[int, ...]  # versions of its networks, oldest first


@dataclass
class _Watch:
    previous: _Flying
    version: int
    ticks_left: int
    fallbacks: int = 0


@dataclass
class OnlineStats:
    rounds_sent: int = 0
    rounds_trained: int = 0
    rounds_failed: int = 0
    accepted: int = 0
    rejected: int = 0
    rollbacks: int = 0
    drops: int = 0  # flying models the monitor replaced by nominal
    crashes: int = 0
    hangs: int = 0
    restarts: int = 0
    windows_superseded: int = 0  # finished windows replaced by a newer one before being sent
    windows_stale: int = 0  # finished windows dropped because the model changed before they were sent
    windows_no_drone_above: int = 0  # wake-only windows not sent: no drone was above in them nor in their replay
    windows_one_point_above: int = 0  # wake-only windows not sent: the drone above stayed at one point of its wake
    pace_wait_s: float = 0.0  # wall time spent holding the simulation back for honest latency
    max_slice_s: float = 0.0  # longest gate/swap slice between two ticks
    late_ticks: int = 0  # ticks whose compute plus the learner's install work before them exceeded the period
    trainer_cpu_s: float = 0.0  # CPU time of the trainer's rounds and jobs (its warm-up before take-off aside)
    gate_jobs: int = 0  # candidates the trainer judged (the rest were judged in the loop's tick gaps)
    swap_s: list[float] = field(default_factory=list)
    install_s: list[float] = field(default_factory=list)
    train_wall_s: list[float] = field(default_factory=list)
    latency_s: list[float] = field(default_factory=list)
