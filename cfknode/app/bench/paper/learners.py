"""The benchmark's learners: none (a fixed model), the paper's lockstep loop, cfknode's
loop with honest latency, and the offline training of a recorded run.

Each is driven by the runner: ``before_tick``/``after_tick`` around a control tick and
``observe`` after every plant step; ``residual`` is the model the MPC uses.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from cfknode.app.bench.paper.formulation import Formulation
from cfknode.app.bench.paper.protocol import PaperProtocol
from cfknode.app.bench.paper.rigid_body_knode import (
    NumpyResidual,
    OneStepPairs,
    QueueWeights,
    RigidBodyQueue,
    fit_output_layer,
    residual_error,
    train_newest,
)
from cfknode.kernel.vehicle import VehicleConfig


@dataclass(frozen=True)
class RoundRecord:
    """One training round of an online learner."""

    window_end: float  # s, sim time the window closed
    start: float  # s, sim time training started
    ready: float  # s, sim time the model was available (lockstep: = window_end)
    swap: float  # s, sim time the model first drove the MPC (nan when rejected or never used)
    wall_time: float  # s, measured training wall time (incl. the gate)
    samples: int
    loss_first: float
    loss_last: float
    accepted: bool
    val_candidate: float = math.nan
    val_current: float = math.nan


class NoLearner:
    """A fixed model (or none): nominal MPC, oracle, offline KNODE-MPC."""

    def __init__(self, residual: NumpyResidual | None = None) -> None:
        self.residual = residual
        self.rounds: list[RoundRecord] = []

    def before_tick(self, t: float) -> None:
        pass

    def after_tick(self, t: float) -> None:
        pass

    def observe(self, step: int, x_before: np.ndarray, u: np.ndarray, x_after: np.ndarray) -> None:
        pass


def _initial_queue(form: Formulation, initial: QueueWeights | None, seed: int) -> RigidBodyQueue:
    """The queue an online learner starts from: the offline model's networks, or none (nominal)."""
    queue = RigidBodyQueue(form.layout, form.dtype, seed)
    if initial is not None and len(initial) and form.online_starts_from == "offline":
        queue = RigidBodyQueue.from_weights(initial, form.dtype, seed)
    return queue


class LockstepLearner:
    """The paper's online loop as its code runs it (docs/paper-code.md#online-loop).

    Rows [x after step k, u_k] are collected from ``collect_from``; when a window of ``t_col``
    closes, the simulation waits while a fresh network is pushed onto the queue and trained
    on that window alone.  The model is loaded after the next tick's solve, so it first
    drives the tick after that.
    """

    def __init__(
        self, protocol: PaperProtocol, form: Formulation, initial: QueueWeights | None, seed: int
    ) -> None:
        self.protocol = protocol
        self.form = form
        self.phys = protocol.vehicle
        self.dt = 1.0 / protocol.plant_hz  # the original's t_step, for its exact float comparisons
        self.queue = _initial_queue(form, initial, seed)
        self.residual = NumpyResidual(self.queue.to_weights()) if len(self.queue) else None
        self._rng = np.random.default_rng(seed)
        self._rows: list[np.ndarray] = []
        self._window = 0
        self._pending: tuple[NumpyResidual, int] | None = None
        self.rounds: list[RoundRecord] = []

    def before_tick(self, t: float) -> None:
        pass

    def after_tick(self, t: float) -> None:
        if self._pending is not None and t > 0.0:
            self.residual, index = self._pending
            self._pending = None
            # It drives the control from the next tick on.
            self.rounds[index] = replace(self.rounds[index], swap=t + 1.0 / self.protocol.control_hz)

    def observe(self, step: int, x_before: np.ndarray, u: np.ndarray, x_after: np.ndarray) -> None:
        form = self.form
        if not step * self.dt > form.collect_from:
            return
        self._rows.append(np.concatenate((x_after, u)))
        if step * self.dt > (self._window + 1) * form.t_col + form.collect_from:
            self._train(step)
            self._rows = []
            self._window += 1

    def _train(self, step: int) -> None:
        form = self.form
        rows = np.asarray(self._rows)
        if form.noise_std > 0.0:
            rows = rows + form.noise_std * self._rng.standard_normal(rows.shape)
        if form.misaligned_pairs:
            pairs = OneStepPairs.from_paper_rows(rows)
        else:  # rows hold x after each step: pair x_{k+1} with u_{k+1} -> x_{k+2}
            pairs = OneStepPairs(np.concatenate((rows[:-1, :13], rows[1:, 13:]), axis=1), rows[1:, :13])
        start = time.perf_counter()
        self.queue.push()
        stats = train_newest(self.queue, pairs, form.online, self.phys)
        self._pending = (NumpyResidual(self.queue.to_weights()), len(self.rounds))
        wall = time.perf_counter() - start
        t_end = (step + 1) * self.dt
        self.rounds.append(RoundRecord(t_end, t_end, t_end, math.nan, wall, len(pairs), stats.loss_first, stats.loss_last, True))


@dataclass
class _Job:
    ready: float
    candidate: RigidBodyQueue | None  # None: rejected by the gate
    index: int


class LatencyLearner:
    """cfknode's online loop with honest latency, simulated exactly in the lockstep harness.

    Aligned samples (x_k, u_k) -> x_{k+1} are cut into windows of ``t_col``.  A finished
    window goes to the trainer as soon as it is free; training starts at max(window end,
    trainer free), and its result is usable at start + the measured training wall time.
    A candidate (warm-started copy of the newest network) must beat the model in use on
    the window's held-out tail; accepted ones are swapped in at the next tick.  The window
    being collected at a swap is discarded, so every window was flown under one model.

    With ``monitor``, every tick also checks the model in use on the samples flown since the
    previous tick: when it predicts them worse than the nominal model (the world changed
    under it, e.g. a second mass change) by ``monitor_margin``, the MPC drops to the nominal model until the next
    accepted candidate; that is a controller change too, so the window restarts.
    """

    def __init__(
        self, protocol: PaperProtocol, form: Formulation, initial: QueueWeights | None, seed: int,
        fixed_latency: float | None = None,
    ) -> None:
        self.protocol = protocol
        self.form = form
        self.phys = protocol.vehicle
        self.dt = protocol.plant_dt
        self.window_steps = int(round(form.t_col * protocol.plant_hz))
        self.fixed_latency = fixed_latency  # tests: a deterministic stand-in for the wall time
        self.queue = _initial_queue(form, initial, seed)
        self.residual = NumpyResidual(self.queue.to_weights()) if len(self.queue) else None
        self._states: list[np.ndarray] = []
        self._inputs: list[np.ndarray] = []
        self._waiting: tuple[OneStepPairs, float] | None = None
        self._job: _Job | None = None
        self._free_at = -math.inf
        self._nominal = RigidBodyQueue(form.layout, form.dtype)  # empty: scores the nominal model
        self._recent: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # steps since the last tick
        self.rounds: list[RoundRecord] = []
        self.drops: list[float] = []  # sim times the monitor dropped the model

    @property
    def _active(self) -> RigidBodyQueue:
        """The model the MPC flies: the queue, or nominal after a monitor drop."""
        return self.queue if self.residual is not None else self._nominal

    def before_tick(self, t: float) -> None:
        recent, self._recent = self._recent, []
        job = self._job
        if job is not None and t >= job.ready - 1e-12:
            self._job = None
            if job.candidate is not None:
                self.queue = job.candidate
                self.residual = NumpyResidual(self.queue.to_weights())
                self.rounds[job.index] = replace(self.rounds[job.index], swap=t)
                self._restart_window()
                return
        if self.form.monitor and self.residual is not None and len(recent) >= 5:
            pairs = OneStepPairs(
                np.array([np.concatenate((x, u)) for x, u, _ in recent]), np.array([x1 for _, _, x1 in recent])
            )
            h = self.form.online.h
            err_model = residual_error(self.queue, pairs, h, self.phys)
            if err_model > self.form.monitor_margin * residual_error(self._nominal, pairs, h, self.phys):
                self.residual = None
                self.drops.append(t)
                self._restart_window()

    def _restart_window(self) -> None:
        if self.form.restart_window_on_swap:
            self._states, self._inputs = [], []

    def after_tick(self, t: float) -> None:
        pass

    def observe(self, step: int, x_before: np.ndarray, u: np.ndarray, x_after: np.ndarray) -> None:
        t_after = (step + 1) * self.dt
        if self.form.monitor:
            self._recent.append((x_before.copy(), np.asarray(u, dtype=float).copy(), x_after.copy()))
        if t_after <= self.form.collect_from + 1e-12:
            return
        if not self._states:
            self._states.append(x_before.copy())
        self._inputs.append(np.asarray(u, dtype=float).copy())
        self._states.append(x_after.copy())
        if len(self._inputs) >= self.window_steps:
            self._waiting = (OneStepPairs.aligned(np.asarray(self._states), np.asarray(self._inputs)), t_after)
            self._states, self._inputs = [], []
        if self._waiting is not None and self._job is None and t_after >= self._free_at - 1e-12:
            self._train(t_after)

    def _train(self, now: float) -> None:
        form = self.form
        pairs, t_end = self._waiting
        self._waiting = None
        start_sim = max(t_end, self._free_at)
        train, val = pairs.split(form.validation_fraction) if form.validation_fraction > 0 else (pairs, pairs)
        t0 = time.perf_counter()
        candidate = copy.deepcopy(self.queue)
        candidate.push(copy_from_newest=form.warm_start)
        stats = train_newest(candidate, train, form.online, self.phys)
        if form.output_ridge > 0.0:
            fit_output_layer(candidate, train, form.online.h, self.phys, form.output_ridge)
        val_new = residual_error(candidate, val, form.online.h, self.phys)
        val_cur = residual_error(self._active, val, form.online.h, self.phys)
        bounded = _bounded(candidate, pairs, form.residual_bound)
        accepted = bool(math.isfinite(val_new) and val_new < val_cur and bounded)
        wall = time.perf_counter() - t0
        latency = wall if self.fixed_latency is None else self.fixed_latency
        ready = start_sim + latency
        self._free_at = ready
        index = len(self.rounds)
        self.rounds.append(
            RoundRecord(t_end, start_sim, ready, math.nan, wall, len(train), stats.loss_first, stats.loss_last,
                        accepted, val_new, val_cur)
        )
        self._job = _Job(ready, candidate if accepted else None, index)


def _bounded(queue: RigidBodyQueue, pairs: OneStepPairs, bound: float) -> bool:
    with torch.no_grad():
        r = queue.residual(torch.as_tensor(pairs.z0, dtype=queue.dtype))
    return bool(torch.isfinite(r).all() and float(r.abs().max()) < bound)


def train_offline(
    form: Formulation, states: np.ndarray, inputs: np.ndarray, vehicle: VehicleConfig, seed: int
) -> tuple[QueueWeights, float]:
    """One network trained on a recorded run: states (m+1, 13), inputs (m, 4) held per step.

    The paper formulation pairs the data as the original does (rows [x_{k+1}, u_k], noise).
    Returns the weights and the training wall time.
    """
    queue = RigidBodyQueue(form.layout, form.dtype, seed)
    if form.misaligned_pairs:
        rows = np.concatenate((states[1:], inputs), axis=1)
        if form.noise_std > 0.0:
            rows = rows + form.noise_std * np.random.default_rng(seed).standard_normal(rows.shape)
        pairs = OneStepPairs.from_paper_rows(rows)
    else:
        pairs = OneStepPairs.aligned(states, inputs)
    queue.push()
    stats = train_newest(queue, pairs, form.offline, vehicle)
    return queue.to_weights(), stats.wall_time
