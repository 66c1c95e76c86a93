"""The online learner's state machine with a scripted trainer: no process, synthetic ticks, exact outcomes."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from cfknode.app.config import load_config
from cfknode.flight.adaptation import AdaptationEstimate
from cfknode.flight.model_slot import ModelSlot
from cfknode.flight.learning.learner import OnlineLearner
from cfknode.flight.learning.trainer_client import TrainerFault
from cfknode.models.modelfile import ModelFile, NetworkWeights, Normalisation
from cfknode.models.residual_np import ResidualQueue
from cfknode.models.trainer_process import TrainOutcome, TrainRequest
from cfknode.app.learning import learner_settings
from fakes import Est, ListLog, Tick

PERIOD = 1.0 / 400.0
TRUE_R = np.array([0.0, 0.0, -2.0])  # the plant: v' = u + TRUE_R


def constant_model(r: np.ndarray, n_networks: int = 1) -> ModelFile:
    """A queue whose residual is ``r`` (each network outputs r / sum of the queue weights)."""
    w = np.exp(np.arange(1, n_networks + 1) - n_networks).sum()
    net = NetworkWeights(((np.zeros((4, 6)), np.zeros(4)), (np.zeros((3, 4)), np.asarray(r) / w)),
                         Normalisation.identity())
    return ModelFile((4,), "tanh", 3, (net,) * n_networks)


class ScriptedTrainer:
    """Stands in for ``TrainerClient``: answers each request with ``answer(request)`` once released."""

    def __init__(self, answer) -> None:
        self.answer = answer
        self.state = "idle"
        self.timeout = 10.0
        self.sent_wall = math.nan
        self.start_wall = math.nan
        self.requests: list[TrainRequest] = []
        self.release = True  # False holds the result back (the trainer is still "training")
        self.fault: TrainerFault | None = None

    @property
    def busy(self) -> bool:
        return self.state == "busy"

    def submit(self, request: TrainRequest) -> None:
        assert self.state == "idle"
        self.requests.append(request)
        self.sent_wall = 0.0
        self.state = "busy"

    def poll(self, timeout: float = 0.0):
        if self.state == "busy" and self.fault is not None:
            self.state, fault, self.fault = "stopped", self.fault, None
            return fault
        if self.state == "busy" and self.release:
            self.state = "idle"
            return self.answer(self.requests[-1])
        return None

    def start(self) -> None:
        self.state, self.start_wall = "idle", 0.0

    def kill(self) -> None:
        self.fault = TrainerFault("crash", "killed")


def outcome_with(model: ModelFile | None, request: TrainRequest) -> TrainOutcome:
    w = request.window
    return TrainOutcome(request.round, request.version, w.version, model, w.t0, w.t1, w.t1, len(w.t) - 1, 0.1,
                        math.nan, math.nan, 2.0, 0.05, 0.05, "" if model is not None else "no usable sample pairs")


class Flight:
    """Synthetic 400 Hz ticks of a vehicle with v' = u + TRUE_R, hovering at 1 m, fed to the learner."""

    def __init__(self, learner: OnlineLearner, slot: ModelSlot) -> None:
        self.learner, self.slot = learner, slot
        self.k = 0
        self.v = np.zeros(3)
        self.rng = np.random.default_rng(0)
        self.r = TRUE_R.copy()  # the plant's residual (a test may change the world mid-flight)
        self.state = "TRACK"  # the supervisor's state the ticks report
        self.layer: Any = None  # the fast layer's estimate the ticks carry (None: no layer)
        self.drag = np.zeros(3)  # per axis, a residual slope in v (1/s) on top of ``r``

    def run(self, seconds: float, source: str = "mpc") -> None:
        for _ in range(int(round(seconds / PERIOD))):
            t = self.k * PERIOD
            u = np.array([0.3 * math.sin(5 * t), 0.2 * math.cos(4 * t), 2.0 + 0.3 * math.sin(3 * t)])
            est = Est(np.array([0.0, 0.0, 1.0 if self.k else 0.0]), self.v.copy())
            self.learner.on_tick(Tick(t, est, u, source, self.slot.version, supervisor_state=self.state,
                                      layer=self.layer(t) if callable(self.layer) else self.layer))
            self.v = self.v + PERIOD * (u + self.r + self.drag * self.v)
            self.k += 1


def make(answer, **online: Any) -> tuple[Flight, OnlineLearner, ScriptedTrainer, ListLog, ModelSlot]:
    # No fast layer flies here: the gate judges whole models, constants included.
    cfg = load_config(overrides={"online.enabled": True, "controller.adaptation": "none",
                                 **{f"online.{k}": v for k, v in online.items()}})
    slot, log, trainer = ModelSlot(None, version=0), ListLog(), ScriptedTrainer(answer)
    learner = OnlineLearner(replace(learner_settings(cfg, lockstep=False), filter_hz=0.0), slot, trainer, log)
    return Flight(learner, slot), learner, trainer, log, slot


def test_a_good_candidate_is_swapped_in_after_enough_fresh_data() -> None:
    flight, learner, trainer, log, slot = make(lambda req: outcome_with(constant_model(TRUE_R), req))
    flight.run(0.5 + 2 * PERIOD)  # the first tick sets the ground; one window of 0.5 s then closes
    assert len(trainer.requests) == 1 and trainer.requests[0].base is None and trainer.requests[0].version == 1
    assert slot.version == 0  # the result is in, but the gate waits for gate_min_pairs fresh samples
    flight.run(0.2)
    assert slot.version == 1 and isinstance(slot.model, ResidualQueue)
    swap = log.topic("/model")[-1]
    assert swap["event"] == "swap" and swap["queue"] == [1] and swap["val_error"] < swap["val_error_current"]
    # The next request builds on the flying model, with the next version number.
    flight.run(0.6)
    assert trainer.requests[1].base is not None and trainer.requests[1].version == 2
    assert trainer.requests[1].window.version == 1 and trainer.requests[1].window.t0 > learner.swaps[0].t


def test_no_backlog_while_the_trainer_is_busy() -> None:
    flight, learner, trainer, _, _ = make(lambda req: outcome_with(constant_model(TRUE_R), req))
    trainer.release = False
    flight.run(2.1)  # four windows close while the first round is still out
    assert len(trainer.requests) == 1
    assert learner.stats.windows_superseded == 2  # windows 2 and 3 were replaced by the newest, 4
    trainer.release = True
    flight.run(0.2)
    # The finished round was swapped in; the waiting window was flown under the old model: dropped.
    assert learner.stats.accepted == 1 and learner.stats.windows_stale == 1


def test_a_worse_candidate_is_rejected_and_learning_goes_on() -> None:
    flight, learner, trainer, log, slot = make(lambda req: outcome_with(constant_model(-TRUE_R), req))
    flight.run(1.2)
    assert slot.version == 0 and learner.stats.rejected >= 1
    assert "not better on held-out data" in log.topic("/model")[0]["reason"]
    assert len(trainer.requests) == 2 and trainer.requests[1].base is None  # still on the nominal model


def test_a_failed_round_is_logged_and_skipped() -> None:
    flight, learner, _, log, slot = make(lambda req: outcome_with(None, req))
    flight.run(0.8)
    assert slot.version == 0 and learner.stats.rounds_failed == 1
    assert log.topic("/training")[0]["ok"] is False
    assert log.topic("/model")[0]["reason"].startswith("training failed")


def test_fallbacks_right_after_a_swap_roll_back_and_stale_results_are_refused() -> None:
    answers: list[Any] = []
    flight, learner, trainer, log, slot = make(lambda req: answers.pop(0)(req), gate=False)
    answers.append(lambda req: outcome_with(constant_model(TRUE_R), req))
    flight.run(0.5 + 5 * PERIOD)
    # Gate off: the window closes at tick 201, its result arrives at 202, folding it is the slice
    # after that, and the tick after that flies it.
    assert slot.version == 1
    flight.run(2 * PERIOD, source="fallback")  # the solver failed twice right after the swap
    assert slot.version == 0 and learner.stats.rollbacks == 1
    assert log.topic("/model")[-1]["event"] == "rollback" and log.topic("/model")[-1]["queue"] == []
    # A round that was trained on the rolled-back model is refused when it comes in.
    answers.append(lambda req: replace(outcome_with(constant_model(TRUE_R), req), base_version=1))
    flight.run(0.8)
    assert learner.rounds[-1].outcome == "reject" and learner.rounds[-1].reason.startswith("stale")


def test_a_model_the_world_changed_under_is_dropped_for_nominal() -> None:
    flight, learner, trainer, log, slot = make(lambda req: outcome_with(constant_model(TRUE_R), req))
    flight.run(0.8)
    assert slot.version == 1 and learner.stats.drops == 0  # the right model is never dropped
    flight.r = np.array([0.0, 0.0, 0.5])  # the world changes (the payload is gone): the model's -2 m/s^2 is wrong
    trainer.answer = lambda req: outcome_with(constant_model(flight.r), req)
    flight.run(0.15)
    assert slot.model is None and slot.version == 2 and learner.stats.drops == 1
    drop = log.topic("/model")[-1]
    assert drop["event"] == "drop" and "worse than nominal" in drop["reason"] and 0.8 < log.messages[-1][1] < 0.95
    assert learner.swaps[-1].kind == "drop" and learner.summary_fields()["models_dropped"] == 1
    flight.run(0.7)
    first_after = trainer.requests[-1]
    assert first_after.base is None and first_after.window.version == 2  # flown under nominal only
    assert slot.version == first_after.version  # and learning goes on from nominal


def test_a_model_flying_when_the_fall_guard_catches_a_lost_thrust_is_dropped_and_its_ticks_not_windowed() -> None:
    flight, learner, trainer, log, slot = make(lambda req: outcome_with(constant_model(TRUE_R), req))
    flight.run(0.8)
    assert slot.version == 1 and slot.model is not None
    windows = learner.recorder.windows
    est = Est(np.array([0.0, 0.0, 1.0]), flight.v.copy())
    for k in range(40):  # the guard flies the clamp: its ticks are flagged saturated and guarded
        learner.on_tick(Tick(flight.k * PERIOD, est, np.array([0.0, 0.0, 5.3]), model_version=slot.version,
                             supervisor_state="TRACK", guarded=True, saturated=True))
        flight.k += 1
    assert slot.model is None and learner.stats.drops == 1 and learner.recorder.windows == windows
    assert "fall guard" in log.topic("/model")[-1]["reason"]


def test_no_window_is_sent_while_the_fast_layer_is_still_learning_the_mass() -> None:
    flight, learner, trainer, _, _ = make(lambda req: outcome_with(constant_model(TRUE_R), req))
    flight.layer = lambda t: AdaptationEstimate(np.zeros(3), 1.0 + 0.1 * min(t, 1.0), np.ones(3))  # moving for 1 s
    flight.run(1.0)
    assert trainer.requests == [] and learner.summary_fields()["windows_unsettled"] == 1
    assert not learner.summary_fields()["online_wake_only"]  # a drone's own air, not a wake above
    flight.run(0.6)  # the window closing at 1.005 s still moved; the next one, settled at 1.1, is trained on
    assert len(trainer.requests) == 1 and learner.summary_fields()["windows_unsettled"] == 2
    assert trainer.requests[0].window.t0 > 1.0


def test_a_candidate_trained_on_a_dropped_model_is_rejected_as_stale() -> None:
    flight, learner, trainer, log, slot = make(lambda req: outcome_with(constant_model(TRUE_R), req))
    flight.run(1.14)  # model 1 flies; the next window closes at 1.14 s and its result waits for fresh data
    flight.r = np.array([0.0, 0.0, 0.5])
    flight.run(0.15)
    assert learner.stats.drops == 1 and slot.model is None
    stale = [r for r in learner.rounds if r.outcome == "reject"]
    assert [r.reason for r in stale] == ["stale: its base 1 was dropped"]
    assert learner.summary_fields()["models_undecided"] == 0  # every trained model was decided


def test_the_monitor_can_be_turned_off() -> None:
    flight, learner, _, _, slot = make(lambda req: outcome_with(constant_model(TRUE_R), req), monitor=False)
    flight.run(0.8)
    flight.r = np.array([0.0, 0.0, 0.5])
    flight.run(0.3)
    assert learner.monitor is None and learner.stats.drops == 0 and slot.version == 1


def test_no_trainer_restart_once_the_flight_is_landing() -> None:
    flight, learner, trainer, log, slot = make(lambda req: outcome_with(constant_model(TRUE_R), req), max_restarts=3)
    flight.state = "LAND"
    trainer.fault = TrainerFault("crash", "trainer process exited (code 70)")
    flight.run(0.6)
    assert learner.stats.crashes == 1 and learner.stats.restarts == 0 and learner.failed
    assert trainer.state == "stopped"  # never started again
    assert [m["event"] for m in log.topic("/model")] == ["crash"]
    assert "not restarted" in log.topic("/events")[-1]["text"]


def test_a_crash_restarts_the_trainer_and_the_window_waits() -> None:
    flight, learner, trainer, log, slot = make(lambda req: outcome_with(constant_model(TRUE_R), req), max_restarts=1)
    trainer.fault = TrainerFault("crash", "trainer process exited (code 70)")
    flight.run(0.6)
    assert learner.stats.crashes == 1 and learner.stats.restarts == 1 and not learner.failed
    assert [m["event"] for m in log.topic("/model")] == ["crash", "restart"]
    flight.run(0.7)
    assert slot.version == 2  # round 1 was lost; round 2 (version 2) flew
    trainer.fault = TrainerFault("hang", "no result within online.trainer_timeout = 10 s; killed")
    flight.run(0.6)
    assert learner.failed and learner.stats.hangs == 1  # restarts exhausted: learning stops, flying goes on
    assert slot.version == 2 and log.topic("/events")[-1]["level"] == "error"


def test_a_starting_model_is_the_first_base() -> None:
    # Without the fast layer, as make(): the gate beside it judges only what varies, and these models are constants.
    cfg = load_config(overrides={"online.enabled": True, "controller.adaptation": "none"})
    start = constant_model(0.5 * TRUE_R, n_networks=2)
    slot, trainer = ModelSlot(ResidualQueue.from_model_file(start), version=1), ScriptedTrainer(
        lambda req: outcome_with(constant_model(TRUE_R, n_networks=3), req))
    log = ListLog()
    learner = OnlineLearner(replace(learner_settings(cfg, lockstep=False), filter_hz=0.0), slot, trainer, log, start)
    Flight(learner, slot).run(0.75)
    assert trainer.requests[0].base is start and trainer.requests[0].version == 2
    assert slot.version == 2 and log.topic("/model")[-1]["queue"] == [1, 1, 2]


def test_collection_starts_at_start_time() -> None:
    flight, learner, trainer, _, _ = make(lambda req: outcome_with(constant_model(TRUE_R), req), start_time=1.0)
    flight.run(1.4)
    assert learner.recorder.windows == 0 and not trainer.requests
    flight.run(0.2)
    assert learner.windows[0][1] == pytest.approx(1.0)


def test_beside_the_layer_an_accepted_model_flies_only_on_the_axes_it_earned() -> None:
    from test_gate_transfer import LAYER_HZ
    from test_online_gate import linear_residual_model

    from cfknode.models.residual_check import SCORE_KEY, flown_axes

    # Drag in x and y is there; the candidate has x's, a sliver of y's (a score too small to fly), and a slope
    # in u_z that is not there (it makes z worse).
    candidate = linear_residual_model(np.diag([-3.0, -0.03, 0.0]), np.diag([0.0, 0.0, 0.5]))
    flight, learner, trainer, log, slot = make(lambda req: outcome_with(candidate, req))
    flight.drag = np.array([-3.0, -3.0, 0.0])
    lenient = replace(learner.s.limits, constant_free=True, steps=5, layer_hz=LAYER_HZ, min_score=0.02)
    learner.s = replace(learner.s, limits=lenient)
    learner._rules = replace(learner._rules, limits=lenient)
    flight.run(0.8)
    assert slot.version == 1
    swap = log.topic("/model")[-1]
    assert swap["event"] == "swap" and swap["score"][0] > 0.02 and swap["score"][2] < 0.0
    # What the fast layer's loop reads: the score, 0 on the axes at or below the gate's min_score.
    score = np.array(swap["score"])
    assert 0.002 < score[1] <= 0.02 and slot.model.beyond_layer[1] == 0.0  # y's sliver: no model flies there
    assert np.allclose(slot.model.beyond_layer, np.where(score > 0.02, score, 0.0))
    assert flown_axes(slot.model.beyond_layer, 0.0) == (True, False, False)
    assert learner.recent_models[-1][1].extra[SCORE_KEY] == swap["score"]


def test_beside_the_layer_an_axis_the_flying_model_stops_earning_on_stops_flying() -> None:
    from test_gate_transfer import LAYER_HZ
    from test_online_gate import linear_residual_model

    from cfknode.models.residual_check import SCORE_KEY, flown_axes

    # Drag in x and y; the candidate has both, and every later round brings it back (rejected: no better than itself).
    candidate = linear_residual_model(np.diag([-3.0, -3.0, 0.0]), np.zeros((3, 3)))
    runs = {}
    for rejudge in (False, True):
        flight, learner, trainer, log, slot = make(lambda req: outcome_with(candidate, req))
        flight.drag = np.array([-3.0, -3.0, 0.0])
        lenient = replace(learner.s.limits, constant_free=True, steps=5, layer_hz=LAYER_HZ, min_score=0.02,
                          rejudge=rejudge)
        learner.s = replace(learner.s, limits=lenient)
        learner._rules = replace(learner._rules, limits=lenient)
        flight.run(0.8)
        assert slot.version == 1 and flown_axes(slot.model.beyond_layer, 0.0) == (True, True, False)
        flight.drag = np.array([-3.0, 0.0, 0.0])  # y's drag is gone: the model's y term now makes y worse
        flight.run(3.0)
        runs[rejudge] = (log.topic("/model"), slot, learner)
    events, slot, _ = runs[False]
    assert not [m for m in events if m["event"] == "narrow"] and slot.version == 1  # off by default
    events, slot, learner = runs[True]
    narrow = [m for m in events if m["event"] == "narrow"]
    assert len(narrow) == 1 and "stopped earning on y" in narrow[0]["reason"], [m.get("reason") for m in events]
    # The same networks fly on under a new version, on x alone (what still earns); the other axes' scores are 0.
    assert slot.version == narrow[0]["version"] > 1
    assert flown_axes(slot.model.beyond_layer, 0.0) == (True, False, False)
    assert slot.model.beyond_layer[0] > 0.02
    # What the flight keeps for the next one is the narrowed file, with the axes it still flies.
    kept = learner.learned_model
    assert kept is not None and np.allclose(kept.extra[SCORE_KEY], slot.model.beyond_layer)


def test_the_flying_model_keeps_an_axis_while_its_score_since_the_swap_is_above_the_bar() -> None:
    from cfknode.flight.learning.rejudge import retired_axes

    flown = np.array([0.3, 0.1, 0.2])
    # Horizontally the gate's bar (0.05 here), vertically any positive share (the inflow's damping scores little).
    assert np.array_equal(retired_axes(flown, np.array([0.06, 0.04, 0.01]), 0.05), [0.3, 0.0, 0.2])
    assert np.array_equal(retired_axes(flown, np.array([-0.2, 0.5, 0.0]), 0.05), [0.0, 0.1, 0.0])
    assert np.array_equal(retired_axes(np.zeros(3), np.ones(3), 0.05), np.zeros(3))  # an axis not flown stays so


def test_a_learned_model_the_log_cannot_take_is_reported_not_raised(tmp_path) -> None:
    from types import SimpleNamespace

    from cfknode.app.learning import keep_learned_model
    from cfknode.models.knode import from_torch_queue
    from test_neighbour_input import neighbour_queue

    learner = SimpleNamespace(learned_model=from_torch_queue(neighbour_queue(9)))
    kept = keep_learned_model(learner, tmp_path / "flight.mcap")
    assert kept == {"learned_model": str(tmp_path / "flight.learned.safetensors")}
    (tmp_path / "flight.cf2.learned.safetensors").mkdir()  # something that is not a file stands in its place
    missing = keep_learned_model(learner, tmp_path / "flight.mcap", "cf2")
    assert list(missing) == ["learned_model_error"] and "not written" in missing["learned_model_error"]
    assert keep_learned_model(SimpleNamespace(learned_model=None), tmp_path / "f.mcap") == {}
    assert keep_learned_model(None, tmp_path / "f.mcap") == {}
