"""Reproducible latency in lockstep (online.latency cpu | fixed): the swap time follows the trainer's report, not the wall."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import pytest

from cfknode.app.config import ConfigError, load_config
from cfknode.flight.model_slot import ModelSlot
from cfknode.flight.learning.learner import OnlineLearner
from cfknode.flight.learning.latency import LatencyPolicy, applied_latency, quantise_up
from cfknode.app.learning import learner_settings
from fakes import ListLog
from test_online_learner import PERIOD, TRUE_R, Flight, ScriptedTrainer, constant_model, outcome_with


def test_quantise_up_rounds_to_the_next_step_and_keeps_exact_multiples() -> None:
    assert quantise_up(0.071, 0.05) == pytest.approx(0.10)
    assert quantise_up(0.10, 0.05) == pytest.approx(0.10)
    assert quantise_up(0.001, 0.05) == pytest.approx(0.05)  # never below one step
    assert quantise_up(0.071, 0.0) == 0.071


def test_applied_latency_per_mode() -> None:
    assert applied_latency(LatencyPolicy("fixed", 0.2), cpu_s=0.07, wall_s=3.0) == 0.2
    assert applied_latency(LatencyPolicy("cpu", quantum_s=0.05), cpu_s=0.07, wall_s=3.0) == pytest.approx(0.1)
    assert applied_latency(LatencyPolicy("wall"), cpu_s=0.07, wall_s=3.0) == 3.0
    assert applied_latency(LatencyPolicy("cpu", quantum_s=0.05), cpu_s=math.nan, wall_s=3.0) == 3.0
    assert LatencyPolicy("fixed", 0.2).floor_s == 0.2 and LatencyPolicy("cpu", quantum_s=0.05).floor_s == 0.05


def test_bad_latency_config_is_a_one_line_error() -> None:
    with pytest.raises(ConfigError, match="online.latency"):
        load_config(overrides={"online.latency": "sometimes"})
    with pytest.raises(ConfigError, match="online.fixed_latency_s"):
        load_config(overrides={"online.fixed_latency_s": -1.0})


class SlowTrainer(ScriptedTrainer):
    """Answers only when the learner blocks on it (poll with a timeout): a result still training in wall terms."""

    def __init__(self, answer) -> None:
        super().__init__(answer)
        self.blocking_polls = 0

    def poll(self, timeout: float = 0.0):
        if self.state == "busy" and timeout <= 0.0:
            return None
        if self.state == "busy":
            self.blocking_polls += 1
        return super().poll(timeout)


def make(trainer_cls: type, cpu_s: float, **online: Any) -> tuple[Flight, OnlineLearner, ScriptedTrainer]:
    # Without the fast layer: beside it the gate judges only what varies, and these models are constants.
    cfg = load_config(overrides={"online.enabled": True, "controller.adaptation": "none",
                                 **{f"online.{k}": v for k, v in online.items()}})
    slot = ModelSlot(None, version=0)
    trainer = trainer_cls(lambda req: replace(outcome_with(constant_model(TRUE_R), req), cpu_s=cpu_s, wall_s=cpu_s))
    settings = replace(learner_settings(cfg, lockstep=True), filter_hz=0.0)
    learner = OnlineLearner(settings, slot, trainer, ListLog(), wall=lambda: 0.0)
    return Flight(learner, slot), learner, trainer


@pytest.mark.parametrize("trainer_cls", [ScriptedTrainer, SlowTrainer])
def test_fixed_latency_swaps_at_send_plus_the_fixed_delay_however_fast_the_trainer(trainer_cls: type) -> None:
    flight, learner, trainer = make(trainer_cls, cpu_s=0.03, latency="fixed", fixed_latency_s=0.2)
    flight.run(1.5)
    first = learner.rounds[0]
    assert first.outcome == "swap" and first.latency_s == 0.2
    # Taken at the tick before send + 0.2 (the next one may fly it), never earlier; then the gate's slices.
    assert first.sent_t + 0.2 - PERIOD - 1e-9 <= first.received_t <= first.sent_t + 0.2 + 1e-9
    assert first.received_t <= first.applied_t < first.received_t + 0.05
    if trainer_cls is SlowTrainer:
        assert trainer.blocking_polls >= 1  # it waited for the result once flight time had come


def test_the_trainer_is_not_asked_again_before_the_result_is_due() -> None:
    flight, learner, trainer = make(ScriptedTrainer, cpu_s=0.03, latency="fixed", fixed_latency_s=0.4)
    flight.run(0.5 + 2 * PERIOD)
    assert len(trainer.requests) == 1
    flight.run(0.3)  # result arrived at once in wall terms, but is due at send + 0.4
    assert len(trainer.requests) == 1 and learner.stats.accepted == 0


def test_cpu_latency_is_the_reported_cpu_time_rounded_up() -> None:
    runs = []
    for trainer_cls in (ScriptedTrainer, SlowTrainer):
        flight, learner, _ = make(trainer_cls, cpu_s=0.07, latency="cpu", latency_quantum_s=0.05)
        flight.run(2.5)
        runs.append([(r.sent_t, r.applied_t, r.outcome) for r in learner.rounds])
        assert learner.rounds[0].latency_s == pytest.approx(0.1)
        assert learner.summary_fields()["online_latency"] == "cpu"
    assert runs[0] == runs[1]  # the same flight whether the result came early or had to be waited for


def test_wall_mode_is_unchanged_and_named() -> None:
    flight, learner, _ = make(ScriptedTrainer, cpu_s=0.07, latency="wall")
    flight.run(1.5)
    assert learner.rounds[0].outcome == "swap"
    assert learner.summary_fields()["online_latency"] == "wall"
