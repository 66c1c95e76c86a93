"""Online learning in a fleet: every drone its own learner, slot and trainer; its models on its own channels;
lockstep with a fixed latency gives the same flight for the same seed."""

from __future__ import annotations

import pytest

from cfknode.app.config import load_config
from cfknode.app.fleet import FleetResult, run_fleet
from cfknode.app.logs.reader import read_log

# Two drones stacked 0.5 m apart with downwash, a short pattern, and a 30 % heavier vehicle from
# t = 2.5 s, so both drones (not only the lower one in the wake) have a residual worth learning.
ONLINE_FLEET = {
    "fleet.size": 2, "fleet.layout": "stack", "sim.downwash.enabled": True,
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
    assert result.drones[0].learner.client.pid != result.drones[1].learner.client.pid  # one trainer each


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
