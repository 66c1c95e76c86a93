"""Fleet flights: the barrier clock, per-drone references, preflight refusals, the coordinator,
and short lockstep flights of two simulated drones (one world, one log, one e-stop each)."""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest

from cfknode.app.config import ConfigError, load_config
from cfknode.app.fleet.flight import FleetCoordinator, drone_configs, preflight, run_fleet
from cfknode.app.logs.reader import read_log
from cfknode.app.radio_budget import LinkLoad, check_radio_budget, radio_of
from cfknode.flight.controller import TickInfo
from cfknode.kernel.fleet_clock import FleetClock
from cfknode.kernel.setpoint import AttitudeSetpoint
from cfknode.safety.separation import SeparationWatch, closest_approach

SHORT = {"trajectory.duration": 1.0, "trajectory.takeoff_duration": 1.5, "trajectory.settle_duration": 0.5,
         "trajectory.land_duration": 1.5, "dashboard.enabled": False}


def fleet_cfg(tmp_path, **over):
    return load_config(None, {**SHORT, "fleet.size": 2, "log.dir": str(tmp_path), "safety.estop_dir": str(tmp_path / "estop"),
                              **over})


class _World:
    def __init__(self):
        self.t = 0.0
        self.calls = []

    def step_to(self, t):
        self.calls.append(t)
        self.t = t


def test_barrier_steps_the_world_only_when_every_loop_waits():
    world = _World()
    clock = FleetClock(world)
    a, b = clock.member(), clock.member()
    seen = []

    async def loop(member, name, period, n):
        for k in range(1, n + 1):
            await member.sleep_until(k * period)
            seen.append((name, member.now()))
        member.leave()

    async def main():
        await asyncio.gather(loop(a, "a", 0.01, 4), loop(b, "b", 0.02, 3))

    asyncio.run(main())
    # Stepped to the earliest request each time; never past a time a loop still wanted.
    assert world.calls == pytest.approx([0.01, 0.02, 0.03, 0.04, 0.06])
    assert [t for n, t in seen if n == "a"] == pytest.approx([0.01, 0.02, 0.03, 0.04])
    assert [t for n, t in seen if n == "b"] == pytest.approx([0.02, 0.04, 0.06])  # b alone once a left


def test_ring_places_drones_evenly_on_the_circle(tmp_path):
    cfg = fleet_cfg(tmp_path, **{"fleet.size": 3})
    names, configs, refs = drone_configs(cfg)
    assert names == ["cf1", "cf2", "cf3"]
    assert [c.radio.uri for c in configs] == ["sim://0", "sim://1", "sim://2"]
    t_pat = refs[0].pattern_window[0] + 0.5
    p = np.array([r.sample(np.array([t_pat])).p[0] for r in refs])
    assert np.allclose(np.linalg.norm(p[:, :2], axis=1), 0.5, atol=1e-9)
    angles = np.sort(np.mod(np.arctan2(p[:, 1], p[:, 0]) - np.arctan2(p[0, 1], p[0, 0]), 2 * np.pi))
    assert angles == pytest.approx([0.0, 2 * np.pi / 3, 4 * np.pi / 3])
    for c, r in zip(configs, refs):  # each starts on the ground right below its own first point
        assert np.allclose(r.sample(np.zeros(1)).p[0], c.sim.initial_position)
    close = closest_approach(names, [r.inner for r in refs])
    assert close.distance == pytest.approx(0.5 * np.sqrt(3), abs=1e-3)


def test_stacked_references_never_come_closer_than_the_spacing_and_land_apart(tmp_path):
    cfg = fleet_cfg(tmp_path, **{"fleet.layout": "stack"})
    names, configs, refs = drone_configs(cfg)
    finals = [r.final_position for r in refs]
    assert np.linalg.norm(finals[0] - finals[1]) == pytest.approx(0.5, abs=1e-6)
    assert closest_approach(names, [r.inner for r in refs]).distance >= 0.3
    assert preflight(cfg, names, configs, refs) == {"sim radio 0": 420.0}


def test_references_too_close_are_refused_naming_the_pair_time_and_distance(tmp_path):
    cfg = fleet_cfg(tmp_path, **{"fleet.layout": "stack", "fleet.ground_spacing": 0.2})
    names, configs, refs = drone_configs(cfg)
    with pytest.raises(ConfigError, match=r"references of cf1 and cf2 come 0\.\d+ m apart at t = [\d.]+ s, "
                                          r"closer than fleet.min_separation 0.3 m"):
        preflight(cfg, names, configs, refs)


def test_radio_budget_assigns_links_by_uri_and_refuses_with_the_numbers():
    assert radio_of("radio://0/80/2M/E7E7E7E701", 2) == "radio 0"
    assert radio_of("radio://1/80/2M/E7E7E7E702", 2) == "radio 1"
    assert [radio_of(f"sim://{n}", 2) for n in range(4)] == ["sim radio 0", "sim radio 0", "sim radio 1", "sim radio 1"]
    loads = [LinkLoad(f"cf{i}", f"radio://0/80/2M/E7E7E7E70{i}", 100.0, 100.0, 10.0) for i in (1, 2)]
    assert check_radio_budget(loads, 500.0, 2) == {"radio 0": 420.0}
    loads.append(LinkLoad("cf3", "radio://0/80/2M/E7E7E7E703", 100.0, 100.0, 10.0))
    with pytest.raises(ConfigError, match=r"radio 0 would carry 630 packets/s \(cf1 210 \+ cf2 210 \+ cf3 210; .*"
                                          r"budget of 500/s"):
        check_radio_budget(loads, 500.0, 2)
    loads[2] = LinkLoad("cf3", "radio://1/80/2M/E7E7E7E703", 100.0, 100.0, 10.0)
    assert check_radio_budget(loads, 500.0, 2) == {"radio 0": 420.0, "radio 1": 210.0}
    with pytest.raises(ConfigError, match="cannot tell which radio"):
        radio_of("udp://localhost:1", 2)


def test_a_fleet_over_its_sim_radios_budget_is_refused_before_anything_connects(tmp_path):
    cfg = fleet_cfg(tmp_path, **{"fleet.size": 3, "fleet.drones_per_sim_radio": 3})
    with pytest.raises(ConfigError, match="sim radio 0 would carry 630 packets/s"):
        run_fleet(cfg)
    assert not list(tmp_path.glob("*.mcap"))


class _Sup:
    def __init__(self):
        self.lands = []
        self.cause = ""

    def request_land(self, reason, cause):
        self.lands.append(cause)

    def snapshot(self):
        return type("S", (), {"cause": self.cause})()

    def interrupt(self):
        pass


class _Log:
    def __init__(self):
        self.events = []

    def write(self, topic, t, msg):
        self.events.append((topic, t, msg))


def _tick(t, p, state):
    est = type("E", (), {"p": np.asarray(p, dtype=float)})()
    return TickInfo(t, est, np.zeros(3), np.zeros(3), np.zeros(3), AttitudeSetpoint(0, 0, 0, 0), "mpc", 0.0, 0.0,
                    False, 0, state)


@pytest.mark.parametrize("policy, expect", [("land_all", ["fleet_fault"]), ("continue", []), ("hold", "held")])
def test_fault_policy_decides_what_the_others_do(tmp_path, policy, expect):
    cfg = fleet_cfg(tmp_path, **{"fleet.on_fault": policy})
    names, _, refs = drone_configs(cfg)
    sups, log = [_Sup(), _Sup()], _Log()
    coord = FleetCoordinator(cfg, names, sups, refs, log)
    coord.on_tick(0, _tick(3.0, [0.5, 0, 1], "TRACK"))
    coord.on_tick(1, _tick(3.0, [-0.5, 0, 1], "TRACK"))
    sups[0].cause = "mocap_lost"
    coord.on_tick(0, _tick(3.1, [0.5, 0, 1], "LAND"))
    coord.on_tick(1, _tick(3.1, [-0.5, 0, 1], "TRACK"))
    assert sups[0].lands == []  # its own supervisor lands it already
    if expect == "held":
        assert refs[1].held_since == pytest.approx(3.1)
        land_start = refs[1].segments["land"][0]
        coord.on_tick(1, _tick(land_start, [-0.5, 0, 1], "TRACK"))
        assert sups[1].lands == ["fleet_fault"]
    else:
        assert sups[1].lands == expect
    assert any("cf1 ended its flight (mocap_lost)" in m["text"] for _, _, m in log.events)


def test_a_pair_too_close_holds_in_place_then_lands(tmp_path):
    cfg = fleet_cfg(tmp_path, **{"fleet.hold_s": 0.5, "trajectory.duration": 10.0})
    names, _, refs = drone_configs(cfg)
    sups, log = [_Sup(), _Sup()], _Log()
    coord = FleetCoordinator(cfg, names, sups, refs, log)
    coord.on_tick(0, _tick(4.0, [0.1, 0, 1], "TRACK"))
    coord.on_tick(1, _tick(4.0, [-0.1, 0, 1], "TRACK"))  # 0.2 m apart
    for k, x in ((0, 0.1), (1, -0.1)):
        ref = refs[k].sample(np.array([4.2, 4.3]))
        assert np.allclose(ref.p, [[x, 0, 1], [x, 0, 1]]) and np.allclose(ref.v, 0.0)
    coord.on_tick(0, _tick(4.25, [0.1, 0, 1], "TRACK"))
    assert sups[0].lands == []
    coord.on_tick(0, _tick(4.5, [0.1, 0, 1], "TRACK"))
    coord.on_tick(1, _tick(4.5, [-0.1, 0, 1], "TRACK"))
    assert sups[0].lands == ["separation"] and sups[1].lands == ["separation"]
    assert coord.watch.closest == pytest.approx(0.2)
    assert "cf1 and cf2 are 0.200 m apart" in log.events[0][2]["text"]


def test_separation_watch_ignores_a_pair_that_is_not_flying():
    watch = SeparationWatch(["a", "b"], 0.3)
    watch.update(0, (0, 0, 0), [False, False])
    assert watch.update(1, (0.1, 0, 0), [False, False]) == []
    assert watch.update(1, (0.1, 0, 0), [True, False]) == [(0, 1, pytest.approx(0.1))]
    assert watch.update(1, (0.1, 0, 0), [True, False]) == []  # once per pair


def test_a_fleet_of_two_flies_lands_and_logs_each_drone_under_its_name(tmp_path):
    result = run_fleet(fleet_cfg(tmp_path))
    assert result.complete, [d.outcome.message for d in result.drones]
    assert result.min_separation_m > 0.3
    for d in result.drones:
        assert d.summary.mse < 1e-3  # a 1 s pattern is mostly ramp; the 30 s acceptance flight is far tighter
        assert d.summary.extra["vehicle_after_shutdown"]["on_ground"]
    data = read_log(result.log_path)
    topics = {name for name, msgs in data.messages.items() if msgs}
    assert {"/cf1/state", "/cf2/state", "/cf1/events", "/summary"} <= topics
    assert not list((tmp_path / "estop").glob("flight-*"))  # every drone's mailbox entry removed


def test_each_drone_of_a_ring_flies_as_it_would_alone_with_its_accelerometer(tmp_path):
    """A fleet drone's link and loop are a single flight's (the accelerometer log too: before, a fleet's drones
    flew without it, and their fast layers and learners never saw a sample). Far apart, no wake reaches either,
    so each flies the very flight it would fly alone on its placed reference."""
    from cfknode.app.mission import run_flight

    cfg = fleet_cfg(tmp_path)
    result = run_fleet(cfg)
    names, configs, refs = drone_configs(cfg)
    for d, c, ref in zip(result.drones, configs, refs):
        alone = run_flight(c, name_hint=f"alone-{d.name}", trajectory=ref, estop=False)
        assert d.summary.extra["imu_samples"] > 0 and d.summary.extra["imu_late"] == 0
        assert d.summary.mse == alone.summary.mse, (d.name, d.summary.mse, alone.summary.mse)


def test_a_fault_in_one_drone_lands_the_others_with_land_all(tmp_path):
    cfg = fleet_cfg(tmp_path, **{"faults.mocap_outages": [{"t": 2.5, "duration": 1.0}]})
    result = run_fleet(cfg)
    causes = [d.outcome.cause for d in result.drones]
    assert causes[0] == "mocap_lost" and causes[1] == "fleet_fault"
    assert all(d.outcome.state.value in ("LANDED", "EMERGENCY") for d in result.drones)
    assert any("fleet.on_fault land_all" in e for e in result.events)


def test_estop_all_reaches_every_drone_of_a_fleet(tmp_path):
    from cfknode.app.commands.estop_all import estop_all

    cfg = fleet_cfg(tmp_path, **{"trajectory.duration": 20.0})
    codes = []

    def operator():
        deadline = time.monotonic() + 60
        from cfknode.safety.estop_mailbox import live_flights

        while len(live_flights(tmp_path / "estop")) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        codes.append(estop_all(tmp_path / "estop", "land", timeout=10.0))

    th = threading.Thread(target=operator, daemon=True)
    th.start()
    result = run_fleet(cfg)
    th.join(5)
    assert codes == [0]
    # 0: every flight took its request. The first drone to read its request lands for it, and the fleet's
    # fault policy (land_all) may land the other for that one tick before it reads its own: either way, by e-stop.
    causes = [d.outcome.cause for d in result.drones]
    assert "estop_land" in causes and set(causes) <= {"estop_land", "fleet_fault"}
    assert all(d.outcome.state.value == "LANDED" for d in result.drones)


def test_downwash_pushes_a_drone_below_down_and_fades_with_distance():
    from cfknode.sim_backend.downwash import downwash_force_z
    from cfknode.sim_backend.settings import DownwashConfig

    cfg = DownwashConfig(enabled=True, peak_fraction=0.15, height=1.0, radius=0.1)
    thrust = 0.33
    right_below = downwash_force_z((0, 0, 1.0), (0, 0, 1.5), thrust, cfg)
    assert right_below == pytest.approx(-0.15 * thrust * 0.5)
    assert downwash_force_z((0, 0, 1.0), (0, 0, 1.2), thrust, cfg) < right_below < 0  # closer: stronger
    assert downwash_force_z((0.1, 0, 1.0), (0, 0, 1.5), thrust, cfg) == pytest.approx(right_below / np.e)
    assert downwash_force_z((0, 0, 1.5), (0, 0, 1.0), thrust, cfg) == 0.0  # the upper one feels nothing
    assert downwash_force_z((0, 0, 0.0), (0, 0, 1.0), thrust, cfg) == 0.0  # beyond its height
    assert downwash_force_z((0, 0, 1.0), (0, 0, 1.5), 0.0, cfg) == 0.0  # motors off: no wake


def test_with_downwash_the_lower_of_two_stacked_drones_sags(tmp_path):
    # The plain MPC shows the wake's push; the fast layer (on by default) would take it out (docs/fleet.md).
    # Both on the ideal plant: the realistic default has its own wake, so "off" would not be off.
    over = {"fleet.layout": "stack", "trajectory.duration": 2.0, "controller.adaptation": "none", "sim.aero": "ideal"}
    off = run_fleet(fleet_cfg(tmp_path, **over))
    on = run_fleet(fleet_cfg(tmp_path, **over, **{"sim.downwash.enabled": True}))
    assert off.complete and on.complete

    def z_error(result, k):
        rec, (t0, t1) = result.drones[k].record, result.drones[k].summary.window
        w = (rec.t >= t0) & (rec.t <= t1)
        return float(np.mean(rec.p[w, 2] - rec.p_ref[w, 2]))

    assert z_error(on, 0) < z_error(off, 0) - 1e-3  # pushed down while right below the other
    assert abs(z_error(on, 1) - z_error(off, 1)) < 1e-3  # the upper drone feels nothing


def test_cli_refuses_a_fleet_over_budget_in_one_line_with_exit_status_2(tmp_path, capsys):
    from cfknode.app.cli import main

    code = main(["fly", "--fleet", "3", "--headless", "--log-dir", str(tmp_path), "--set", "fleet.drones_per_sim_radio=3"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err[-1].startswith("cfknode: error: take-off refused: sim radio 0 would carry 630 packets/s")
