"""Installing a trained candidate: fold it into numpy, filter the fresh data, judge it (the gate).

The same steps run in one of two places. In the flight process they are a generator, one slice per
tick gap (``install_steps``). Handed to the trainer process (``gate_job``, through
``TrainerClient.submit_job``) they take none of the loop's tick gaps: there they ran up to 1.5 ms of
CPU each, beside a tick of about 0.9 ms in a 2.5 ms period. The trainer is idle while a candidate is
judged (the learner sends no window meanwhile), and it runs below the flight's priority on a wall clock.

The trainer also counts the slices the generator took, so a lockstep flight applies the verdict at the
very tick the slices would have ended: which process judged a candidate never changes a simulated flight.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Generator

import numpy as np

from cfknode.flight.learning.gate import GateLimits, GateVerdict, gate_pairs, gate_steps
from cfknode.models.modelfile import ModelFile
from cfknode.models.residual_np import ResidualQueue
from cfknode.models.trainer_process import Job, JobOutcome, TrainOutcome, Window


@dataclass(frozen=True)
class GateRules:
    """What the gate needs from the learner's settings (picklable: it travels with a ``gate_job``)."""

    gate: bool  # False: every trained model flies (the paper)
    filter_hz: float  # training.velocity_filter_hz, as the training data was filtered
    limits: GateLimits


# (t, x, u) recorded after the training window, and the neighbour's relative position when recorded
Fresh = tuple[np.ndarray, ...]


def held_out_tail(out: TrainOutcome, window: Window) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The part of the training window the trainer held out (samples from its last training sample on): the
    paper's gate data, where no fresh data exists."""
    k = int(np.searchsorted(window.t, out.train_t1 - 1e-9))
    return window.t[k:], window.x[k:], window.u[k:]


def install_steps(candidate_file: ModelFile, current: Any | None, window: Window, fresh: Fresh,
                  rules: GateRules) -> Generator[None, None, tuple[GateVerdict, ResidualQueue]]:
    """Fold the candidate, filter the held-out data, then the gate: each a slice of its own.

    Returns the verdict and the folded candidate. ``current``: the flying model (None: nominal)."""
    candidate = ResidualQueue.from_model_file(candidate_file)
    yield
    if not rules.gate:  # gate off is the paper: every trained model flies
        return GateVerdict(True, "", math.nan, math.nan, math.nan, math.nan, 0), candidate
    ft, fx, fu, *nb = fresh
    pairs = gate_pairs(ft, fx, fu, rules.filter_hz, nb[0] if nb else None)
    yield
    verdict = yield from gate_steps(candidate_file, candidate, current, pairs, np.concatenate((window.x, fx)),
                                    np.concatenate((window.u, fu)), rules.limits)
    return verdict, candidate


def gate_job(candidate_file: ModelFile, current: Any | None, window: Window, fresh: Fresh,
             rules: GateRules) -> tuple[GateVerdict, int]:
    """``install_steps`` at once, in the trainer process: the verdict, and how many slices (calls of
    ``next``, the last one finishing) the flight loop would have spent on it."""
    steps = install_steps(candidate_file, current, window, fresh, rules)
    calls = 0
    while True:
        calls += 1
        try:
            next(steps)
        except StopIteration as done:
            return done.value[0], calls


class TrainerJudging:
    """The learner's side of a gate the trainer runs: send the job, wait or poll for it, apply it on time.

    Mixed into ``OnlineLearner``, which owns the state these read (``client``, ``s``, ``_gating``, ...)."""

    client: Any
    s: Any
    stats: Any
    _gating: Any
    _wall: Callable[[], float]
    _rules: GateRules
    _held_rules: GateRules | None = None  # for data the layer held on (``_rules_for``)
    recorder: Any
    _on_event: Callable[[Any, float], None]
    _reject: Callable[[float, Any, str, GateVerdict | None], None]
    _finish_gate: Callable[[float, Any, GateVerdict, float], None]
    _job = 0  # id of the newest job sent to the trainer
    _job_out = False  # its answer not yet read: the trainer is busy with it

    def _rules_for(self, after: float) -> GateRules:
        """The gate's rules for the fresh data after ``after``: where the fast layer measured nothing on most of it
        (held near the floor), the layer supplied no constant, so constants count there."""
        if self._held_rules is not None and self.recorder.held_share(after) >= 0.5:
            return self._held_rules
        return self._rules

    def _send_gate_job(self, g: Any, current: Any | None, fresh: Fresh, rules: GateRules | None = None) -> None:
        """Hand the candidate ``g`` to the trainer to judge by ``rules`` (None: the learner's), when it can (else
        its slices run here)."""
        if not judged_remotely(self.client, current) or self.client.state != "idle":
            return
        self._job += 1
        g.job, self._job_out = self._job, True
        self.stats.gate_jobs += 1
        held = g.held
        rules = self._rules if rules is None else rules
        self.client.submit_job(Job(g.job, gate_job, (held.outcome.model, current, held.window, fresh, rules)))

    def _step_judged(self, t: float, g: Any, start: float) -> None:
        """A tick gap of a candidate the trainer judges. In lockstep the verdict applies on the tick its slices
        would have ended here (the flight waits for it, in wall time only); on a wall clock once it is in."""
        g.calls += 1
        if g.verdict is None and self.s.lockstep:
            self._await_job(t)
            start = self._wall()  # the wait is pacing (simulated wall time), not the loop's work
        if self._gating is not g or g.verdict is None:
            return  # still on its way, or lost with the trainer (rejected there)
        verdict, calls = g.verdict
        if self.s.lockstep and g.calls < calls:
            return
        self._gating = None
        if verdict.accepted:  # the same fold as the trainer's, of the same file: the flying copy
            assert g.held.outcome.model is not None
            g.candidate = ResidualQueue.from_model_file(g.held.outcome.model)
        self._finish_gate(t, g, verdict, start)

    def _await_job(self, t: float) -> None:
        """Lockstep: wait for the outstanding job's answer (or the fault that loses it); time spent is pacing."""
        waited = self._wall()
        while self._job_out and self.client.state == "busy":
            event = self.client.poll(self.client.timeout)
            if event is not None:
                self._on_event(event, t)
        self.stats.pace_wait_s += self._wall() - waited

    def _on_job(self, event: JobOutcome, t: float) -> None:
        self.stats.trainer_cpu_s += event.cpu_s
        if event.id == self._job:
            self._job_out = False
        g = self._gating
        if g is None or g.job != event.id:
            return  # its candidate was discarded meanwhile (rollback, drop)
        if event.error:
            self._gating = None
            self._reject(t, g.held, f"the gate failed: {event.error}", None)
            return
        g.verdict = event.value

    def _lose_job(self, t: float, kind: str) -> None:
        """The trainer is gone (a crash, a hang): a candidate it was judging is rejected, unjudged."""
        self._job_out = False
        g = self._gating
        if g is not None and g.job and g.verdict is None:
            self._gating = None
            self._reject(t, g.held, f"not judged: the trainer judging it was lost ({kind})", None)

def judged_remotely(client: Any, current: Any | None) -> bool:
    """Whether the trainer can judge a candidate: a client that runs jobs, and a flying model that can
    travel to it (nominal, or the numpy queue the learner folds; another loop's own model stays here)."""
    return bool(getattr(client, "runs_jobs", False)) and (current is None or type(current) is ResidualQueue)


__all__ = ["Fresh", "GateRules", "TrainerJudging", "gate_job", "held_out_tail", "install_steps", "judged_remotely"]
