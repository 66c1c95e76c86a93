"""Online learning in a fleet: every drone its own learner, slot and trainer; its models on its own channels;
lockstep with a fixed latency gives the same flight for the same seed."""

from __future__ import annotations

import pytest

from cfknode.app.config import load_config
from cfknode.app.fleet.flight import FleetResult, run_fleet
from cfknode.app.logs.reader import read_log

# Two drones stacked 0.5 m apart with downwash, a short pattern, and a 30 % heavier vehicle from
# t = 2.5 s, so both drones (not only the lower one in the wake) have a residual worth learning. The
# paper's method (no fast layer): beside the layer a mass is the layer's, and nothing is left to learn.
ONLINE_FLEET = {
    "controller.adaptation": "none",
    "fleet.size": 2, "fleet.layout": "stack", "sim.aero": "ideal", "sim.downwash.enabled": True,
    "trajectory.duration": 2.5, "trajectory.takeoff_duration": 1.5, "trajectory.settle_duration": 0.5,
    "trajectory.land_duration": 1.5, "dashboard.enabled": False,
    "sim.mass_changes": [{"t": 2.5, "factor": 1.3}],
    "online.enabled": True, "online.t_col": 0.25, "online.latency": "fixed", "online.fixed_latency_s": 0.1,
}


def _fly(tmp_path) -> FleetResult:
    return run_fleet(load_config(None, {**ONLINE_FLEET, "log.dir": str(tmp_path),
                                        "safety.estop_dir": str(tmp_path / "estop")}))


@pytest.fixture(scope="module")
def flights(tmp_path_factory) -> tuple[FleetResult, FleetResult]:
    return _fly(tmp_path_factory.mktemp("a")), _fly(tmp_path_factory.mktemp("b"))


def test_each_drone_learns_its_own_models_and_lands(flights) -> None:
    result = flights[0]
    assert result.complete, [d.outcome.message for d in result.drones]
    learners = [d.learner for d in result.drones]
    assert learners[0] is not learners[1] and learners[0].slot is not learners[1].slot
    for d in result.drones:
        s = d.summary.extra
        assert s["controller"] == "knode-mpc-online" and s["online_latency"] == "fixed"
        assert s["models_accepted"] >= 1, d.name
        assert s["trainer_crashes"] == 0 and not s["trainer_failed"]
        assert all(r.latency_s == 0.1 for r in d.learner.rounds if r.outcome != "lost")
    assert result.drones[0].learner.client.pid == result.drones[1].learner.client.pid  # one shared trainer


def test_each_drones_models_go_to_its_own_channels(flights) -> None:
    result = flights[0]
    data = read_log(result.log_path)
    for d in result.drones:
        swaps = [m for m in data.messages.get(f"/{d.name}/model", []) if m["event"] == "swap"]
        assert len(swaps) == d.summary.extra["models_accepted"]
        assert len(data.messages.get(f"/{d.name}/training", [])) == d.summary.extra["windows_sent"] - \
            d.summary.extra["rounds_in_flight"]
        [summary] = data.messages[f"/{d.name}/summary"]
        assert summary["extra"]["models_accepted"] == d.summary.extra["models_accepted"]
    assert not data.messages.get("/model") and not data.messages.get("/training")  # nothing unattributed


def test_the_same_seed_flies_the_same_fleet(flights) -> None:
    a, b = flights
    for da, db in zip(a.drones, b.drones):
        assert da.summary.mse == db.summary.mse, da.name
        assert da.summary.mse_z == db.summary.mse_z, da.name
        assert da.summary.extra["models_accepted"] == db.summary.extra["models_accepted"]


def test_a_shared_trainer_answers_each_port_and_a_crash_loses_only_the_queued_rounds() -> None:
    import dataclasses

    import numpy as np

    from cfknode.app.config import FaultInjection
    from cfknode.app.learning import trainer_settings
    from cfknode.flight.learning.shared_trainer import SharedTrainer
    from cfknode.flight.learning.trainer_client import TrainerFault
    from cfknode.models.trainer_process import TrainerReady, TrainOutcome, TrainRequest, Window

    def window(residual: float, index: int) -> Window:
        t = 2.0 + np.arange(201) / 400.0
        u = np.stack([0.8 * np.sin(4 * t), 0.6 * np.cos(3 * t), 0.5 * np.sin(6 * t)], axis=1)
        v = np.cumsum(u + [0.0, 0.0, residual], axis=0) / 400.0
        return Window(index, t, np.concatenate((np.cumsum(v, axis=0) / 400.0, v), axis=1), u, 0)

    def wait(port, timeout=60.0):
        for _ in range(int(timeout / 0.5)):
            msg = port.poll(0.5)
            if msg is not None:
                return msg
        raise AssertionError("no message")

    settings = trainer_settings(load_config(overrides={"online.enabled": True}))
    shared = SharedTrainer(dataclasses.replace(settings, inject=FaultInjection(crash_at_round=3, hang_at_round=0,
                                                                               nan_at_round=0)), 30.0, 2)
    a, b = shared.ports
    try:
        shared.start()
        assert shared.wait_ready(120.0) and a.state == b.state == "idle"
        a.submit(TrainRequest(1, 11, window(-2.0, 1), (), None, 0.0))
        b.submit(TrainRequest(1, 21, window(+2.0, 1), (), None, 0.0))  # queued behind a's round
        assert a.state == b.state == "busy"
        out_b, out_a = wait(b), wait(a)  # read in any order: each port gets its own
        assert isinstance(out_a, TrainOutcome) and isinstance(out_b, TrainOutcome)
        assert (out_a.version, out_b.version) == (11, 21) and a.state == b.state == "idle"
        assert out_a.max_abs_residual > 1.0 and out_b.max_abs_residual > 1.0

        b.submit(TrainRequest(3, 22, window(+2.0, 2), (), None, 0.0))  # the injected crash
        fault = wait(b)
        assert isinstance(fault, TrainerFault) and fault.kind == "crash"
        assert a.poll(0.0) is None and a.state == "starting"  # a lost nothing; it waits for the restart
        b.start()  # b's learner restarts it
        assert isinstance(wait(a), TrainerReady) and isinstance(wait(b), TrainerReady)
        a.submit(TrainRequest(2, 12, window(-2.0, 2), (), out_a.model, 0.0))
        assert wait(a).version == 12 and shared.client.starts == 2
    finally:
        shared.close()


def test_each_drone_keeps_the_model_it_learned_beside_the_log(flights) -> None:
    # The next flight starts from it (--model): a fleet's drones each keep their own, named for the drone.
    from pathlib import Path

    from cfknode.models.modelfile import load_model

    result = flights[0]
    kept = 0
    for d in result.drones:
        model = d.learner.learned_model
        if model is None:
            assert "learned_model" not in d.summary.extra
            continue
        path = Path(d.summary.extra["learned_model"])
        assert path == Path(result.log_path).with_suffix(f".{d.name}.learned.safetensors")
        loaded = load_model(path)
        assert len(loaded.networks) == len(model.networks)
        assert all((a == b).all() for n, m in zip(loaded.networks, model.networks)
                   for (a, _), (b, _) in zip(n.layers, m.layers))
        kept += 1
    assert kept >= 1
