"""Online learning in closed loop: short lockstep flights through the whole stack with the trainer process.

``fly_online`` flies through ``cfknode.app.mission.run_flight``, exactly as ``cfknode fly --online`` does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from cfknode.app.config import Config, load_config
from cfknode.app.logs.writer import check_message, read_log
from cfknode.flight.loop import FlightRecord
from cfknode.flight.learning.learner import OnlineLearner
from cfknode.app.ui.summary import FlightSummary
from cfknode.app.mission import run_flight

# The default 0.5 m circle, shortened; the mass grows 30 % one second into the pattern (t = 3 s).
SHORT = {
    "trajectory.duration": 5.0,
    "trajectory.takeoff_duration": 1.5,
    "trajectory.settle_duration": 0.5,
    "trajectory.land_duration": 1.5,
    "trajectory.ramp_duration": 0.5,
    "sim.mass_changes": [{"t": 3.0, "factor": 1.3}],
    "online.enabled": True,
    "controller.adaptation": "none",  # the paper's method: the learner alone (with the layer: test_learner_with_layer.py)
}


@dataclass(frozen=True)
class Flight:
    summary: FlightSummary
    record: FlightRecord
    learner: OnlineLearner | None
    versions: np.ndarray  # model version each tick flew with
    ticks_t: np.ndarray


class VersionTap:
    """Records which model version flew each tick (observes after the learner)."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.v: list[int] = []

    def on_tick(self, tick: Any) -> None:
        self.t.append(tick.t)
        self.v.append(tick.model_version)


def fly_online(cfg: Config, name: str = "online") -> Flight:
    """A flight through run_flight, with a tap recording the model version of every tick."""
    tap = VersionTap()
    res = run_flight(cfg, name_hint=name, observers=[tap])
    return Flight(res.summary, res.record, res.learner, np.asarray(tap.v), np.asarray(tap.t))


def _config(tmp_path, **overrides: Any) -> Config:
    return load_config(overrides={**SHORT, "log.dir": str(tmp_path), **overrides})


@pytest.fixture(scope="module")
def online(tmp_path_factory) -> Flight:
    # online.latency wall: this flight checks the realistic mode, paced by the trainer's wall time.
    return fly_online(_config(tmp_path_factory.mktemp("online"), **{"online.latency": "wall"}))


@pytest.fixture(scope="module")
def nominal(tmp_path_factory) -> Flight:
    return fly_online(_config(tmp_path_factory.mktemp("nominal"), **{"online.enabled": False}), "nominal")


@pytest.fixture(scope="module")
def faulty(tmp_path_factory) -> Flight:
    """NaN candidate in round 1 (gate on), trainer crash in round 2, hang in round 4 (1 s timeout).

    Restarts are paced like training (a restart costs flight time: ~3-6 s of torch import here),
    so this flight is long enough for both restarts to complete.
    """
    cfg = _config(tmp_path_factory.mktemp("faulty"), **{
        "online.inject": {"nan_at_round": 1, "crash_at_round": 2, "hang_at_round": 4},
        "online.trainer_timeout": 1.0,
        "trajectory.duration": 8.0,
    })
    return fly_online(cfg, "faulty")


# --- the normal online flight ------------------------------------------------------------------


def test_online_flight_learns_and_swaps(online: Flight) -> None:
    s, learner = online.summary.extra, online.learner
    assert s["models_trained"] >= 3 and s["models_accepted"] >= 2
    decided = s["models_accepted"] + s["models_rejected"]
    assert decided + s["models_undecided"] == s["models_trained"] + s["training_failed"]
    assert s["trainer_crashes"] == 0 and s["models_rolled_back"] == 0
    assert online.summary.extra["fallback_ticks"] == 0
    assert s["online_mode"].startswith("honest latency")
    assert learner.slot.version == s["final_model_version"] > 0


def test_windows_never_span_a_swap(online: Flight) -> None:
    learner = online.learner
    assert len(learner.windows) >= 5
    for index, t0, t1, version in learner.windows:
        flown = online.versions[(online.ticks_t >= t0 - 1e-9) & (online.ticks_t <= t1 + 1e-9)]
        assert flown.size > 0 and np.all(flown == version), (index, t0, t1, set(flown))
    for swap in learner.swaps:
        assert not any(t0 <= swap.t < t1 for _, t0, t1, _ in learner.windows)


def first_tick_with(flight: Flight, version: int, after: float) -> int:
    k = int(np.searchsorted(flight.ticks_t, after, side="right"))
    assert flight.versions[k] == version and flight.versions[k - 1] != version
    return k


def test_models_are_applied_no_earlier_than_window_end_plus_training_time(online: Flight) -> None:
    period = 1.0 / 400.0
    swapped = [r for r in online.learner.rounds if r.outcome == "swap"]
    assert swapped
    for r in swapped:
        assert r.sent_t >= r.window[1]  # sent when the window closed, or once the previous candidate was decided
        assert r.latency_s >= r.train_wall_s > 0
        # Pacing: the simulation never ran ahead of the trainer's wall time.
        assert r.received_t <= r.sent_t + r.latency_s + 2 * period + 1e-9, r
        # The swap happens between ticks: the next tick is the first to fly the new version,
        # and it is no earlier than the window's end plus the measured round trip.
        k = first_tick_with(online, r.version, r.applied_t)
        assert online.ticks_t[k] >= r.sent_t + r.latency_s - 1e-9 >= r.window[1] + r.train_wall_s - 1e-9
        # ... nor much later: the gate waits for its fresh data and runs in slices of a tick gap.
        gate_wait = max(r.latency_s, (online.learner.s.gate_min_pairs + 1) * period)
        assert online.ticks_t[k] <= r.sent_t + gate_wait + 40 * period, r


def test_a_swap_adds_no_missed_tick(online: Flight) -> None:
    # In lockstep a tick cannot be late, so check the structure: every tick of the grid ran, through
    # every swap, and the swap work is spread over tick gaps (timings are reported, not asserted).
    period = 1.0 / 400.0
    index = np.floor(online.record.t / period + 1e-9).astype(int)
    np.testing.assert_array_equal(np.diff(index), 1)
    assert online.summary.extra["fallback_ticks"] == 0
    for swap in online.learner.swaps:
        first_tick_with(online, swap.version, swap.t)
    assert online.summary.extra["install_slice_max_ms"] is not None


def test_the_log_records_models_and_training(online: Flight) -> None:
    log = read_log(online.summary.log_path)
    models, training = log.topic("/model"), log.topic("/training")
    assert len(training) == online.summary.extra["models_trained"] + online.summary.extra["training_failed"]
    swaps = [m for m in models if m["event"] == "swap"]
    assert len(swaps) == online.summary.extra["models_accepted"]
    for msg in models:
        assert check_message("/model", msg) == []
    for msg in training:
        assert check_message("/training", msg) == []
        assert msg["t_col"] == 0.5 and msg["train_wall_s"] > 0
    assert all(m["val_error"] < m["val_error_current"] for m in swaps)
    assert all("reason" in m for m in models if m["event"] == "reject")
    assert log.topic("/summary")[0]["extra"]["models_trained"] == online.summary.extra["models_trained"]


def test_online_learning_beats_nominal_after_a_mass_change(online: Flight, nominal: Flight) -> None:
    # The z error left by a 30 % heavier vehicle is what the residual learns; report both in the failure.
    assert nominal.learner is None
    assert online.summary.mse_z < 0.7 * nominal.summary.mse_z, (online.summary.mse_z, nominal.summary.mse_z)
    assert online.summary.mse < nominal.summary.mse


# --- faults ----------------------------------------------------------------------------------


def test_nan_candidate_is_rejected_by_the_gate(faulty: Flight) -> None:
    first = faulty.learner.rounds[0]
    assert first.round == 1 and first.outcome == "reject" and first.reason == "non-finite weights"
    assert faulty.summary.extra["fallback_ticks"] == 0


def test_trainer_crash_restarts_and_the_flight_goes_on(faulty: Flight) -> None:
    s = faulty.summary.extra
    # The injected hang is found by a wall-clock timeout (a hung process has no other sign), so on a loaded
    # machine a slow round may time out too: every such extra is a hang, restarted, never a crash.
    assert s["trainer_crashes"] == 1 and s["trainer_hangs"] >= 1
    assert s["trainer_restarts"] == s["trainer_crashes"] + s["trainer_hangs"]
    assert not s["trainer_failed"]
    lost = {r.round: r.reason for r in faulty.learner.rounds if r.outcome == "lost"}
    assert "exited" in lost[2] and "trainer_timeout" in lost[4]
    assert all("trainer_timeout" in why for k, why in lost.items() if k != 2)
    # After the crash the restarted trainer trained a round as usual (round 3 unless load timed it out).
    third = next(r for r in faulty.learner.rounds if r.round > 2 and r.outcome in ("swap", "reject"))
    assert third.train_wall_s > 0
    log = read_log(faulty.summary.log_path)
    events = [m["event"] for m in log.topic("/model")]
    assert events.count("crash") == events.count("restart") == s["trainer_restarts"]
    ready = [e for e in log.topic("/events") if e.get("source") == "online" and "trainer ready" in e["text"]]
    assert ready and ready[0]["t"] <= third.sent_t  # the crash restart came up (the hang's may outlast the flight)
    assert faulty.summary.extra["fallback_ticks"] == 0  # the flight never noticed


def test_solver_failure_after_a_swap_rolls_back(tmp_path) -> None:
    # Gate off (the paper: every model flies): the NaN model reaches the MPC, which fails, and is rolled back.
    cfg = _config(tmp_path, **{"online.gate": False, "online.inject": {"nan_at_round": 2, "crash_at_round": 0,
                                                                        "hang_at_round": 0},
                               "trajectory.duration": 3.0})
    flight = fly_online(cfg, "rollback")
    s, learner = flight.summary.extra, flight.learner
    assert s["models_rolled_back"] == 1
    rollback = next(sw for sw in learner.swaps if sw.kind == "rollback")
    bad = next(r for r in learner.rounds if r.round == 2)
    assert bad.outcome == "swap"
    # Exactly rollback_fallbacks ticks flew the fallback, then the previous model came back.
    assert flight.summary.extra["fallback_ticks"] == cfg.online.rollback_fallbacks
    k = int(np.searchsorted(flight.ticks_t, rollback.t + 1e-9))
    assert flight.versions[k] == rollback.version != bad.version
    model_events = read_log(flight.summary.log_path).topic("/model")
    assert any(m["event"] == "rollback" and "fallbacks" in m["reason"] for m in model_events)


def test_fixed_latency_takes_each_result_at_send_plus_the_delay_unpaced(tmp_path) -> None:
    period = 1.0 / 400.0
    cfg = _config(tmp_path, **{"online.latency": "fixed", "online.fixed_latency_s": 0.2, "trajectory.duration": 3.0})
    flight = fly_online(cfg, "fixed")
    s = flight.summary.extra
    assert s["online_latency"] == "fixed" and "fixed 0.2 s" in s["online_mode"]
    decided = [r for r in flight.learner.rounds if r.outcome in ("swap", "reject")]
    assert len(decided) >= 2
    for r in decided:
        assert r.latency_s == 0.2
        # Taken at the tick whose successor may fly it: exactly send + 0.2 in flight time, whatever the wall did.
        assert r.sent_t + 0.2 - period - 1e-9 <= r.received_t <= r.sent_t + 0.2 + 1e-9, r
    assert flight.summary.extra["fallback_ticks"] == 0


def test_paper_lockstep_applies_each_model_at_its_window_end(tmp_path) -> None:
    cfg = _config(tmp_path, **{"online.paper_lockstep": True, "trajectory.duration": 2.0})
    flight = fly_online(cfg, "paper")
    s = flight.summary.extra
    assert s["online_mode"].startswith("paper-lockstep (reproduction only")
    rounds = flight.learner.rounds
    assert len(rounds) >= 3
    for r in rounds:
        if r.outcome == "swap":
            assert r.applied_t == pytest.approx(r.window[1])  # the simulation waited: zero sim-time latency
    assert all(math.isfinite(r.rmse_candidate) for r in rounds if r.outcome in ("swap", "reject"))


def test_the_flight_keeps_the_model_it_learned_beside_its_log(online: Flight) -> None:
    # What the next flight starts from (--model); a flight that ends on the nominal model writes none.
    from pathlib import Path

    from cfknode.models.modelfile import load_model

    model = online.learner.learned_model
    assert model is not None
    path = Path(online.summary.extra["learned_model"])
    assert path == Path(online.summary.log_path).with_suffix(".learned.safetensors")
    assert len(load_model(path).networks) == len(model.networks)
