"""A fleet on Ray (``cfknode fly --fleet N --executor ray``): each drone an actor on the node with its radio.

The cluster is ``ray.cluster_utils.Cluster`` on this machine: two nodes of one CPU, one simulated
radio each (``crazyradio_0``, ``crazyradio_1``), shared by the tests of this module.
"""

from __future__ import annotations

import threading
import time

from types import SimpleNamespace

import numpy as np
import pytest

from cfknode.app.config import ConfigError, load_config
from cfknode.app.fleet.ray_fleet import check_resources, radio_resource

SHORT = {"trajectory.duration": 1.0, "trajectory.takeoff_duration": 1.5, "trajectory.settle_duration": 0.5,
         "trajectory.land_duration": 1.5, "trajectory.ramp_duration": 0.5, "dashboard.enabled": False,
         "fleet.drones_per_sim_radio": 1}


HARNESS_GUARD_S = 300.0


def fleet_cfg(tmp_path, **over):
    return load_config(None, {**SHORT, "fleet.size": 2, "log.dir": str(tmp_path / "logs"),
                              "safety.estop_dir": str(tmp_path / "estop"), **over})


def test_each_drone_needs_the_resource_named_for_its_radio(tmp_path):
    cfg = fleet_cfg(tmp_path, **{"fleet.drones_per_sim_radio": 2})
    assert [radio_resource(cfg, f"sim://{n}") for n in range(4)] == ["crazyradio_0", "crazyradio_0",
                                                                     "crazyradio_1", "crazyradio_1"]
    lab = load_config(None, {"fleet.ray_radio_resource": "lab-a_radio{radio}"})
    assert radio_resource(lab, "radio://3/80/2M/E7E7E7E701") == "lab-a_radio3"


def test_a_bad_resource_name_scheme_is_refused_in_one_line():
    with pytest.raises(ConfigError, match="fleet.ray_radio_resource"):
        load_config(None, {"fleet.ray_radio_resource": "radio_{index}"})


def test_a_drone_whose_radio_no_node_offers_is_refused_naming_it():
    available = {"CPU": 2.0, "crazyradio_0": 1.0, "node:10.0.0.1": 1.0}
    check_resources(["cf1", "cf2"], ["crazyradio_0", "crazyradio_0"], available)  # both on radio 0: fine
    with pytest.raises(ConfigError) as err:
        check_resources(["cf1", "cf2", "cf3"], ["crazyradio_0", "crazyradio_1", "crazyradio_1"], available)
    line = str(err.value)
    assert "\n" not in line and "take-off refused" in line
    assert "cf2 and cf3 need the Ray resource 'crazyradio_1'" in line and "custom resources: crazyradio_0" in line


class _FakeLink:
    """What the driver's coordinator calls on a drone's actor, recorded."""

    def __init__(self):
        self.calls, self.cause = [], ""

    def snapshot(self):
        return self

    def request_land(self, reason, cause):
        self.calls.append(("land", cause))

    def land_at(self, t, reason, cause):
        self.calls.append(("land_at", round(t, 3), cause))


class _FakeRef:
    def __init__(self, ref):
        self.segments, self.held = ref.segments, []

    def hold(self, t, p):
        self.held.append(t)


def _tick(t, state, p=None):
    return SimpleNamespace(t=t, supervisor_state=state, est=None if p is None else SimpleNamespace(p=np.array(p)))


def test_the_driver_coordinator_sends_holds_and_timed_landings_to_the_actors(tmp_path):
    from cfknode.app.fleet.flight import drone_configs
    from cfknode.app.fleet.ray_fleet import RemoteCoordinator

    cfg = fleet_cfg(tmp_path, **{"fleet.on_fault": "land_all", "fleet.hold_s": 0.5, "trajectory.duration": 10.0})
    names, _, refs = drone_configs(cfg)
    links, held = [_FakeLink(), _FakeLink()], [_FakeRef(r) for r in refs]
    log = SimpleNamespace(write=lambda *a: None)
    co = RemoteCoordinator(cfg, names, links, held, log)
    co.on_tick(0, _tick(3.0, "TRACK", [0.0, 0.0, 1.0]))
    co.on_tick(1, _tick(3.1, "TRACK", [0.1, 0.0, 1.0]))  # 0.1 m apart: both hold, then land 0.5 s later
    assert [h.held for h in held] == [[3.1], [3.1]]
    assert [k.calls for k in links] == [[("land_at", 3.6, "separation")]] * 2
    co.on_tick(0, _tick(3.7, "TRACK", [0.0, 0.0, 1.0]))  # the actor keeps the time: nothing more from here
    assert links[0].calls == [("land_at", 3.6, "separation")]
    links[1].cause = "mocap_lost"
    co.on_tick(1, _tick(4.0, "LAND"))  # a fault of its own: the others land (fleet.on_fault land_all)
    assert links[0].calls[-1] == ("land", "fleet_fault") and any("cf2 ended its flight (mocap_lost)" in e
                                                                  for e in co.events)


def test_the_timeline_compares_drones_at_the_same_flight_time_however_far_apart_their_actors_run(tmp_path):
    from cfknode.app.fleet.flight import drone_configs
    from cfknode.app.fleet.ray_fleet import RemoteCoordinator, Timeline

    cfg = fleet_cfg(tmp_path, **{"trajectory.duration": 10.0})
    names, _, refs = drone_configs(cfg)
    links = [_FakeLink(), _FakeLink()]
    co = RemoteCoordinator(cfg, names, links, [_FakeRef(r) for r in refs], SimpleNamespace(write=lambda *a: None))
    line = Timeline(co, links)
    # cf1 runs ahead: at 3 s it is where cf2 is at 1 s. Compared as the replies arrive they would
    # be 0 m apart; at the same flight time they are 2 m apart (1 m with the one-tick lag of the
    # one-process fleet, at these 1 s ticks).
    line.add(0, [(t, "TRACK", "", (t, 0.0, 1.0)) for t in (1.0, 2.0, 3.0)])
    line.add(1, [(1.0, "TRACK", "", (3.0, 0.0, 1.0))])
    line.feed()
    assert co.events == [] and co.watch.closest == pytest.approx(2.0)  # t = 1 s only: cf2 holds the rest back
    line.add(1, [(t, "TRACK", "", (t + 2.0, 0.0, 1.0)) for t in (2.0, 3.0)])
    line.close(0, "LANDED", "")
    line.close(1, "LANDED", "")
    line.feed()
    assert co.events == [] and co.watch.closest >= 1.0
    assert [k.calls for k in links] == [[], []]


def test_the_drivers_view_tells_every_drones_flight_time_and_an_ended_one_holds_none_back():
    from cfknode.app.fleet.ray_fleet import FleetView

    view = FleetView(2, SimpleNamespace(_spots={}))
    view.seen(0, SimpleNamespace(p=(0.5, 0.0, 1.0), state="TRACK", spot=None, t=2.0))
    view.seen(1, SimpleNamespace(p=None, state="", spot=None, t=0.0))  # not ticked yet
    told = [[], []]
    actors = [SimpleNamespace(fleet_view=SimpleNamespace(remote=lambda *a, k=k: told[k].append(a))) for k in (0, 1)]
    view.push(actors, [True, False])  # cf2's flight has not started to be counted as flying: not told
    assert told == [[([(0.5, 0.0, 1.0), None], ["TRACK", ""], {}, [2.0, 0.0])], []]
    view.ended(0, "LANDED")
    view.seen(0, SimpleNamespace(p=(0.5, 0.0, 0.0), state="LANDED", spot=None, t=4.0))  # a late reply
    view.push(actors, [False, True])
    assert told[1][-1][1:] == (["LANDED", ""], {}, [float("inf"), 0.0])


def test_an_operators_status_call_takes_no_tick_from_the_drivers_separation_watch():
    """``ray.get_actor(name).status()`` (an operator, a test) used to take the ticks the driver's report
    was to carry: the separation watch never saw them."""
    from collections import deque

    from cfknode.app.fleet.drone_actor import DroneActor, DroneStatus

    actor = DroneActor.__new__(DroneActor)  # its calls alone, without Ray's runtime
    actor._lock = threading.Lock()
    actor._status = DroneStatus("cf1", 0.005, (0.0, 0.0, 0.1), "TAKEOFF", "", 2, False, False, "node")
    actor._trail = deque([(0.0025, "TAKEOFF", "", (0.0, 0.0, 0.1)), (0.005, "TAKEOFF", "", (0.0, 0.0, 0.1))])
    assert actor.status().t == 0.005 and actor.status().trail == ()
    assert [tick[0] for tick in actor.report().trail] == [0.0025, 0.005]  # the driver has both
    assert actor.report().trail == ()  # each tick once


@pytest.mark.parametrize("argv, expect", [
    (["--executor", "ray"], "--executor ray flies a fleet (--fleet N, N >= 2); a single flight runs here"),
    (["--fleet", "2", "--address", "127.0.0.1:6379"], "--address needs --executor ray"),
])
def test_cli_refuses_executor_options_that_do_not_fit_in_one_line(tmp_path, capsys, argv, expect):
    from cfknode.app.cli import main

    code = main(["fly", "--headless", "--log-dir", str(tmp_path), *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err[-1] == f"cfknode: error: {expect}"


ray = pytest.importorskip("ray")


@pytest.fixture(scope="module")
def cluster():
    from ray.cluster_utils import Cluster

    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "resources": {"crazyradio_0": 1}})
    c.add_node(num_cpus=1, resources={"crazyradio_1": 1})
    c.wait_for_nodes()
    ray.init(address=c.address, logging_level="warning", log_to_driver=False)
    try:
        yield c
    finally:
        ray.shutdown()
        c.shutdown()


def _settings(cluster):
    from cfknode.app.bench.executor import ExecutorSettings

    return ExecutorSettings(kind="ray", address=cluster.address)


def _node_with(resource: str) -> str:
    return next(n["NodeID"] for n in ray.nodes() if n["Alive"] and n["Resources"].get(resource))


def _tracking_actor(drone: str):
    """The drone's actor (found by its name) once its drone flies the pattern (the guard only keeps a
    broken build from hanging the run: actors start slowly on a loaded machine)."""
    deadline = time.monotonic() + HARNESS_GUARD_S
    actor = None
    while time.monotonic() < deadline and actor is None:
        names = [n for n in ray.util.list_named_actors() if f"-{drone}-" in n]
        actor = ray.get_actor(names[0]) if names else None
        time.sleep(0.1)
    assert actor is not None
    while time.monotonic() < deadline and ray.get(actor.status.remote()).state != "TRACK":
        time.sleep(0.05)
    assert ray.get(actor.status.remote()).state == "TRACK", f"{drone} never flew its pattern"
    return actor


def test_two_drones_fly_one_per_radio_node_land_and_log_on_their_node(cluster, tmp_path):
    from cfknode.app.fleet.ray_fleet import run_fleet_ray
    from cfknode.app.logs.reader import read_log

    result = run_fleet_ray(fleet_cfg(tmp_path), _settings(cluster))
    assert result.complete, [d.outcome.message for d in result.drones]
    nodes = [d.summary.extra["ray_node"] for d in result.drones]
    assert nodes == [_node_with("crazyradio_0"), _node_with("crazyradio_1")] and nodes[0] != nodes[1]
    for d in result.drones:
        (path,) = d.summary.extra["logs"]
        log = read_log(path)
        assert not log.truncated and 0.9 * d.record.ticks < len(log.topic("/state")) <= d.record.ticks
        assert log.topic("/summary")[-1]["mse"] == pytest.approx(d.summary.mse) and d.summary.mse < 1e-3
    assert 0.3 < result.min_separation_m < 1.1  # opposite on the 0.5 m circle, tick by tick
    fleet_log = read_log(result.log_path)
    assert set(fleet_log.topic("/summary")[-1]["logs"]) == {"cf1", "cf2"}


def test_a_drone_whose_radio_no_node_has_is_refused_before_any_actor_starts(cluster, tmp_path):
    from cfknode.app.fleet.ray_fleet import run_fleet_ray

    with pytest.raises(ConfigError, match=r"take-off refused: cf3 needs the Ray resource 'crazyradio_2'"):
        run_fleet_ray(fleet_cfg(tmp_path, **{"fleet.size": 3}), _settings(cluster))
    assert not (tmp_path / "logs").exists() or not list((tmp_path / "logs").glob("*.mcap"))


def test_a_restarted_actor_keeps_the_old_log_and_ends_its_drone_as_a_fault(cluster, tmp_path):
    from cfknode.app.fleet.drone_actor import RESTART_CAUSE
    from cfknode.app.fleet.ray_fleet import run_fleet_ray
    from cfknode.app.logs.reader import read_log

    cfg = fleet_cfg(tmp_path, **{"trajectory.duration": 8.0})
    out: dict = {}
    driver = threading.Thread(target=lambda: out.update(result=run_fleet_ray(cfg, _settings(cluster))), daemon=True)
    driver.start()
    cf1 = _tracking_actor("cf1")
    ray.kill(cf1, no_restart=False)  # the worker dies mid-air; Ray restarts the actor
    driver.join(HARNESS_GUARD_S)  # a hang guard, not a timing test
    result = out["result"]
    one, two = result.drones
    assert any("cf1 ended its flight (actor_lost); fleet.on_fault land_all" in e for e in result.events)
    assert one.outcome.cause == RESTART_CAUSE, one.outcome.message
    assert two.outcome.cause == "fleet_fault"  # fleet.on_fault land_all
    assert two.outcome.state.value == "LANDED"
    old, new = one.summary.extra["logs"]
    assert new.endswith("-restart.mcap") and old != new
    before = read_log(old)  # the crash left it without its footer: read around the damage, never overwritten
    assert before.truncated and len(before.topic("/state")) > 0
    after = read_log(new)
    assert after.topic("/events")[0]["kept_logs"] == [old]


def test_estop_all_reaches_every_actor_through_the_driver(cluster, tmp_path):
    from cfknode.app.commands.estop_all import estop_all
    from cfknode.app.fleet.ray_fleet import run_fleet_ray

    cfg = fleet_cfg(tmp_path, **{"trajectory.duration": 8.0})
    out: dict = {}
    driver = threading.Thread(target=lambda: out.update(result=run_fleet_ray(cfg, _settings(cluster))), daemon=True)
    driver.start()
    _tracking_actor("cf1")
    _tracking_actor("cf2")
    assert estop_all(tmp_path / "estop", "land", timeout=10.0) == 0  # the driver's entries sim-cf1, sim-cf2
    driver.join(HARNESS_GUARD_S)  # a hang guard, not a timing test
    result = out["result"]
    # 0: every flight took its request. The first drone to read its request lands for it, and the fleet's
    # fault policy (land_all) may land the other for that one tick before it reads its own: either way, by e-stop.
    causes = [d.outcome.cause for d in result.drones]
    assert "estop_land" in causes and set(causes) <= {"estop_land", "fleet_fault"}
    assert all(d.outcome.state.value == "LANDED" for d in result.drones)
    assert all(d.record.t[-1] < 8.0 for d in result.drones)  # landed well before the mission's end


def test_a_stacked_ray_fleet_stopped_mid_flight_lands_bottom_up_as_a_local_fleet_does(cluster, tmp_path):
    """Two actors stacked in one column (0.7 and 1.3 m), ``cfknode estop --all --land`` mid-pattern: the
    top drone glides clear of the one below before it descends (before, each actor landed straight down
    on its own, and cf2 came down onto cf1). The pattern is slow (0.05 m/s), so the column stays one
    column however far apart the two actors' lockstep clocks run when the stop reaches them."""
    from cfknode.app.commands.estop_all import estop_all
    from cfknode.app.fleet.flight import drone_configs
    from cfknode.app.fleet.ray_fleet import run_fleet_ray
    from test_fleet_stack import _airborne_min_separation

    cfg = fleet_cfg(tmp_path, **{"fleet.layout": "stack", "trajectory.height": 0.7, "trajectory.duration": 8.0,
                                 "trajectory.speed": 0.05, "fleet.stack_spacing": 0.6})
    out: dict = {}
    driver = threading.Thread(target=lambda: out.update(result=run_fleet_ray(cfg, _settings(cluster))), daemon=True)
    driver.start()
    _tracking_actor("cf1")
    _tracking_actor("cf2")
    assert estop_all(tmp_path / "estop", "land", timeout=10.0) == 0
    driver.join(HARNESS_GUARD_S)  # a hang guard, not a timing test
    result = out["result"]
    first_landing = min(r.segments["land"][0] for r in drone_configs(cfg)[2])  # the mission's own, lowest first
    for d in result.drones:
        assert d.outcome.state.value == "LANDED" and d.outcome.cause in ("estop_land", "fleet_fault"), d.outcome.message
        # Stopped mid-flight, not at the mission's end: the stop took before the mission's first landing was due
        # (the upper drone's record ends later: it waits for the lower one, then descends from 1.3 m).
        assert d.outcome.t < first_landing
        assert d.summary.extra["view_wait_s"] >= 0.0  # how long its loop waited for the view before descending
    assert _airborne_min_separation(result) >= cfg.fleet.min_separation
    ends = [d.record.p[d.record.ticks - 1] for d in result.drones]
    assert np.hypot(*(ends[0][:2] - ends[1][:2])) >= cfg.fleet.min_separation  # side by side on the ground


def test_online_learning_is_refused_for_a_ray_fleet_before_ray_starts(tmp_path):
    from cfknode.app.bench.executor import ExecutorSettings
    from cfknode.app.config import ConfigError, load_config
    from cfknode.app.fleet.ray_fleet import run_fleet_ray

    cfg = load_config(overrides={"fleet.size": 2, "online.enabled": True, "log.dir": str(tmp_path)})
    with pytest.raises(ConfigError, match="executor local"):
        run_fleet_ray(cfg, ExecutorSettings(kind="ray", jobs=2, address=None))
