"""The trainer process judges the candidates and runs below the flight: none of the gate's work takes the
loop's tick gaps, a lockstep flight swaps on the same tick as when the loop judged, and the trainer's priority
and threads are what a wall-clock flight needs."""

from __future__ import annotations

import math
import os
from dataclasses import replace
from typing import Any

import numpy as np

import cfknode.flight.learning.install as install
from cfknode.app.config import load_config
from cfknode.app.learning import learner_settings, trainer_settings
from cfknode.flight.learning.install import GateRules, gate_job, install_steps
from cfknode.flight.learning.learner import OnlineLearner
from cfknode.flight.learning.trainer_client import TrainerClient, TrainerFault
from cfknode.flight.model_slot import ModelSlot
from cfknode.models.residual_np import ResidualQueue
from cfknode.models.trainer_process import Job, JobOutcome, Window, run_job
from fakes import ListLog
from test_online_learner import TRUE_R, Flight, ScriptedTrainer, constant_model, outcome_with


class JudgingTrainer(ScriptedTrainer):
    """A scripted trainer that also runs the learner's jobs, in this process, when polled (as the child would)."""

    runs_jobs = True

    def __init__(self, answer: Any) -> None:
        super().__init__(answer)
        self.jobs: list[Job] = []  # every job sent
        self.pending: Job | None = None  # the job not yet answered
        self.inside = False  # True while a job runs: "in the trainer"
        self.hold = False  # True: a job stays unanswered (the trainer is still judging)

    def submit_job(self, job: Job) -> None:
        assert self.state == "idle"
        self.jobs.append(job)
        self.pending, self.state = job, "busy"

    def poll(self, timeout: float = 0.0) -> Any:
        if self.pending is None or self.state != "busy":
            return super().poll(timeout)
        if self.fault is not None:
            self.pending = None  # lost with the process
            return super().poll(timeout)
        if self.hold:
            return None
        self.inside = True
        try:
            done = run_job(self.pending)
        finally:
            self.inside = False
        self.pending, self.state = None, "idle"
        return done


def _learner(trainer: Any, lockstep: bool, **online: Any) -> tuple[Flight, OnlineLearner, ListLog, ModelSlot]:
    cfg = load_config(overrides={"online.enabled": True, "controller.adaptation": "none",
                                 **{f"online.{k}": v for k, v in online.items()}})
    slot, log = ModelSlot(None, version=0), ListLog()
    learner = OnlineLearner(replace(learner_settings(cfg, lockstep=lockstep), filter_hz=0.0), slot, trainer, log)
    return Flight(learner, slot), learner, log, slot


def _answers() -> Any:
    """Good, worse, good again: both verdicts, and a second swap on top of a flying model."""
    models = iter([constant_model(TRUE_R), constant_model(-TRUE_R), constant_model(TRUE_R)])
    return lambda req: outcome_with(next(models, constant_model(TRUE_R)), req)


def test_the_trainer_judges_every_candidate_and_lockstep_swaps_on_the_same_tick(monkeypatch) -> None:
    judging = JudgingTrainer(_answers())
    where: list[bool] = []  # for every gate run: whether it ran inside the trainer
    real = install.gate_steps

    def gate_steps(*args: Any) -> Any:
        where.append(judging.inside)
        return (yield from real(*args))

    monkeypatch.setattr(install, "gate_steps", gate_steps)
    flight, learner, log, slot = _learner(judging, lockstep=True)
    flight.run(2.0)
    assert len(judging.jobs) == 3 and where == [True, True, True]
    # The same flight with the loop judging (a client that runs no jobs): the same swaps on the same ticks.
    where.clear()
    ref_flight, ref, ref_log, ref_slot = _learner(ScriptedTrainer(_answers()), lockstep=True)
    ref_flight.run(2.0)
    assert where == [False, False, False]
    assert [(s.t, s.version, s.kind) for s in learner.swaps] == [(s.t, s.version, s.kind) for s in ref.swaps]
    assert [(r.round, r.outcome, r.reason, r.applied_t) for r in learner.rounds] == \
        [(r.round, r.outcome, r.reason, r.applied_t) for r in ref.rounds]
    assert learner.stats.accepted >= 1 and learner.stats.rejected >= 1 and slot.version == ref_slot.version
    assert [m["event"] for m in log.topic("/model")] == [m["event"] for m in ref_log.topic("/model")]


def test_on_a_wall_clock_the_verdict_applies_once_it_is_in() -> None:
    judging = JudgingTrainer(lambda req: outcome_with(constant_model(TRUE_R), req))
    flight, learner, _, slot = _learner(judging, lockstep=False)
    flight.run(0.75)
    assert len(judging.jobs) == 1 and slot.version == 1 and isinstance(slot.model, ResidualQueue)
    assert learner.swaps[0].kind == "swap"


def test_a_trainer_lost_while_judging_rejects_the_candidate_and_restarts() -> None:
    judging = JudgingTrainer(lambda req: outcome_with(constant_model(TRUE_R), req))
    flight, learner, log, slot = _learner(judging, lockstep=False, max_restarts=1)
    judging.hold = True
    while not judging.jobs:
        flight.run(0.01)
    judging.fault, judging.hold = TrainerFault("crash", "trainer process exited (code 70)"), False
    flight.run(0.05)
    assert learner.stats.crashes == 1 and learner.stats.restarts == 1 and slot.version == 0
    assert log.topic("/model")[0]["event"] == "reject" and "not judged" in log.topic("/model")[0]["reason"]
    flight.run(0.8)  # learning goes on: the next window's candidate is judged and flies
    assert slot.version > 0 and learner.stats.accepted == 1


def test_a_gate_that_raises_in_the_trainer_rejects_its_candidate() -> None:
    judging = JudgingTrainer(lambda req: outcome_with(constant_model(TRUE_R), req))
    flight, learner, log, slot = _learner(judging, lockstep=False)
    learner._rules = replace(learner._rules, limits=None)  # type: ignore[arg-type] - the gate raises on it
    flight.run(0.75)
    assert slot.version == 0 and learner.stats.rejected == 1
    assert log.topic("/model")[0]["reason"].startswith("the gate failed: AttributeError")


def test_the_trainer_is_niced_on_a_wall_clock_only_and_preloads_the_gate() -> None:
    lockstep = load_config(overrides={"online.enabled": True})
    realtime = load_config(overrides={"online.enabled": True, "sim.realtime": True, "online.trainer_nice": 7})
    assert trainer_settings(lockstep).nice == 0  # the lockstep loop waits for the trainer: never lower it
    assert trainer_settings(realtime).nice == 7
    assert "cfknode.flight.learning.install" in trainer_settings(realtime).preload


def _gate_inputs() -> tuple[Any, ...]:
    rng = np.random.default_rng(1)
    n = 241
    t = np.arange(n) / 400.0
    u = rng.normal(0.0, 1.0, (n, 3))
    v = np.cumsum((u + TRUE_R) / 400.0, axis=0)
    x = np.concatenate((np.zeros((n, 3)), v), axis=1)
    window = Window(1, t[:200], x[:200], u[:200], 0)
    cfg = load_config(overrides={"online.enabled": True, "controller.adaptation": "none"})
    rules = GateRules(True, 0.0, learner_settings(cfg, lockstep=True).limits)
    return constant_model(TRUE_R), None, window, (t[200:], x[200:], u[200:]), rules


def test_a_niced_single_threaded_trainer_judges_as_the_loop_would() -> None:
    settings = replace(trainer_settings(load_config(overrides={"online.enabled": True})), nice=3)
    client = TrainerClient(settings, timeout=120.0, start_timeout=300.0)  # torch on a loaded machine
    client.start()
    try:
        assert client.wait_ready(300.0), client.start_problem
        assert client.ready is not None and client.ready.threads == 1
        expected = min(19, os.getpriority(os.PRIO_PROCESS, 0) + 3)
        assert client.ready.nice == expected and os.getpriority(os.PRIO_PROCESS, client.pid) == expected
        args = _gate_inputs()
        client.submit_job(Job(1, gate_job, args))
        answer = None
        while answer is None:
            answer = client.poll(120.0)
        assert isinstance(answer, JobOutcome) and answer.id == 1 and answer.error == "" and client.state == "idle"
        steps, calls, here = install_steps(*args), 0, None
        while here is None:
            calls += 1
            try:
                next(steps)
            except StopIteration as done:
                here = done.value[0]
        verdict, remote_calls = answer.value
        assert verdict.accepted and repr(verdict) == repr(here) and remote_calls == calls  # repr: NaN fields
        assert math.isfinite(answer.cpu_s)
    finally:
        client.close()
