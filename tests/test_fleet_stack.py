"""A stacked fleet: every placed trajectory is checked against the fence before take-off, and the
fleet never lands one drone onto another (it glides clear of those below, then lands)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from cfknode.app.config import ConfigError, load_config
from cfknode.app.fleet.flight import drone_configs, placed_fence_events, preflight, run_fleet
from cfknode.app.fleet.coordinator import LANDING_CLEARANCE, FleetCoordinator
from cfknode.flight.controller import TickInfo
from cfknode.flight.formation import HoldableReference
from cfknode.flight.trajectory import make_trajectory
from cfknode.kernel.setpoint import AttitudeSetpoint
from cfknode.safety.landing_spot import below, clear_spot

SHORT = {"trajectory.duration": 1.0, "trajectory.takeoff_duration": 1.5, "trajectory.settle_duration": 0.5,
         "trajectory.land_duration": 1.5, "dashboard.enabled": False}


def stack_cfg(tmp_path, size=3, **over):
    return load_config(None, {**SHORT, "fleet.size": size, "fleet.layout": "stack", "log.dir": str(tmp_path),
                              "safety.estop_dir": str(tmp_path / "estop"), **over})


# --- before take-off ----------------------------------------------------------------------------


def test_a_stacked_drone_above_the_fence_is_refused_in_one_line_naming_it(tmp_path):
    cfg = stack_cfg(tmp_path)  # levels 1.0, 1.5, 2.0 m; the soft box ends at 1.8 m
    names, _, refs = drone_configs(cfg)
    with pytest.raises(ConfigError) as err:
        placed_fence_events(cfg, names, refs)
    text = str(err.value)
    assert "\n" not in text and text.startswith("refusing to take off: cf3's placed trajectory")
    assert "z = 2.00 m, beyond the fence's 1.80 m" in text and "--force" in text


def test_forced_it_flies_clamped_with_an_event_and_the_clamped_stack_is_checked_for_separation(tmp_path):
    cfg = stack_cfg(tmp_path, **{"hardware.force": True})
    names, configs, refs = drone_configs(cfg)
    events = placed_fence_events(cfg, names, refs)
    assert len(events) == 1 and "take-off FORCED" in events[0]["text"] and "cf3" in events[0]["text"]
    preflight(cfg, names, configs, refs)  # clamped to 1.8 m: 0.30 m above cf2, not closer than 0.3 m
    tighter = stack_cfg(tmp_path, **{"hardware.force": True, "fleet.min_separation": 0.35})
    with pytest.raises(ConfigError, match="references of cf2 and cf3 come 0.3[0-4][0-9] m apart"):
        preflight(tighter, *drone_configs(tighter))


def test_the_cli_refuses_the_stack_with_exit_status_2(tmp_path, capsys):
    from cfknode.app.cli import main

    code = main(["fly", "--fleet", "3", "--fleet-layout", "stack", "--headless", "--log-dir", str(tmp_path),
                 "--set", f"safety.estop_dir={tmp_path / 'estop'}", "--duration", "5"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "cf3's placed trajectory" in err[0]


# --- where a drone lands ------------------------------------------------------------------------


def test_clear_spot_is_the_nearest_point_clear_of_the_drones_below():
    lo, hi = np.array([-1.3, -1.3, -0.2]), np.array([1.3, 1.3, 1.8])
    p = np.array([0.5, 0.0, 1.5])
    assert np.array_equal(clear_spot(p, [[1.2, 0.0, 1.0]], 0.45, lo, hi), p)  # clear already: stays
    spot = clear_spot(p, [[0.5, 0.0, 1.0]], 0.45, lo, hi, away_from=(0.0, 0.0))
    assert spot[2] == 1.5 and np.hypot(*(spot[:2] - [0.5, 0.0])) == pytest.approx(0.45)
    assert spot[0] == pytest.approx(0.95)  # outward, away from the pattern's centre
    # Near the fence it goes the other way; boxed in by drones everywhere, there is none.
    spot = clear_spot([1.2, 0.0, 1.5], [[1.2, 0.0, 0.0]], 0.45, lo, hi, away_from=(0.0, 0.0))
    assert np.all(spot[:2] <= hi[:2]) and np.hypot(*(spot[:2] - [1.2, 0.0])) >= 0.45 - 1e-9
    ring = [[0.5 + 0.3 * np.cos(a), 0.3 * np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, 40)]
    assert clear_spot(p, ring, 2.0, lo, hi) is None
    assert [q[2] for q in below(p, [[0, 0, 1.0], None, [0, 0, 1.6]])] == [1.0]


def test_a_held_reference_glides_to_its_spot_starting_and_ending_at_rest(tmp_path):
    cfg = stack_cfg(tmp_path)
    ref = HoldableReference(make_trajectory(cfg.trajectory, (0.5, 0.0, 0.0)))
    ref.hold(3.0, [0.5, 0.0, 1.0], to=[0.95, 0.0, 1.0], move_s=1.0)
    s = ref.sample(np.array([3.0, 3.5, 4.0, 5.0]))
    assert np.allclose(s.p[:, 0], [0.5, 0.725, 0.95, 0.95]) and np.allclose(s.p[:, 2], 1.0)
    assert np.allclose(s.v[[0, 2, 3]], 0.0) and s.v[1, 0] == pytest.approx(1.875 * 0.45)
    assert np.array_equal(ref.hold_target, [0.95, 0.0, 1.0])


class _Sup:
    def __init__(self):
        self.lands = []

    def request_land(self, reason, cause):
        self.lands.append(cause)

    def snapshot(self):
        return type("S", (), {"cause": ""})()


class _Log:
    def write(self, topic, t, msg):
        pass


def _tick(t, p, state):
    est = type("E", (), {"p": np.asarray(p, dtype=float)})()
    return TickInfo(t, est, np.zeros(3), np.zeros(3), np.zeros(3), AttitudeSetpoint(0, 0, 0, 0), "mpc", 0.0, 0.0,
                    False, 0, state)


def test_a_close_pair_in_a_stack_glides_clear_of_every_drone_below_then_lands(tmp_path):
    cfg = stack_cfg(tmp_path, **{"trajectory.duration": 10.0, "hardware.force": True})
    names, _, refs = drone_configs(cfg)
    sups = [_Sup(), _Sup(), _Sup()]
    coord = FleetCoordinator(cfg, names, sups, refs, _Log())
    column = [[0.5, 0.0, 1.0], [0.5, 0.0, 1.5], [0.5, 0.0, 1.78]]  # cf2 and cf3 0.28 m apart
    for i, p in enumerate(column):
        coord.on_tick(i, _tick(4.0, p, "TRACK"))
    clearance = LANDING_CLEARANCE * cfg.fleet.min_separation
    spot2, spot3 = refs[1].hold_target, refs[2].hold_target
    assert np.hypot(*(spot2[:2] - [0.5, 0.0])) >= clearance - 1e-9  # clear of cf1's column
    for q in ([0.5, 0.0], spot2[:2]):  # cf3: clear of cf1, cf2 and where cf2 lands
        assert np.hypot(*(spot3[:2] - q)) >= clearance - 1e-9
    assert refs[0].held_since is None  # cf1 flies on
    coord.on_tick(1, _tick(4.0 + cfg.fleet.hold_s, spot2, "TRACK"))
    assert sups[1].lands == []  # still gliding: it lands once at its spot
    for i, p in ((0, column[0]), (1, spot2), (2, spot3)):
        coord.on_tick(i, _tick(6.0, p, "TRACK"))
    assert sups[1].lands == ["separation"] and sups[2].lands == ["separation"]


def test_a_drone_does_not_descend_while_a_flying_drone_is_right_below(tmp_path):
    cfg = stack_cfg(tmp_path, size=2, **{"trajectory.duration": 10.0, "fleet.on_fault": "land_all"})
    names, _, refs = drone_configs(cfg)
    sups = [_Sup(), _Sup()]
    coord = FleetCoordinator(cfg, names, sups, refs, _Log())
    coord.on_tick(0, _tick(4.0, [0.5, 0.0, 1.0], "TRACK"))
    coord.on_tick(1, _tick(4.0, [1.2, 1.2, 1.5], "TRACK"))
    coord._schedule_land(1, 4.1, "test", "fleet_fault")  # due, but cf1 flies right below it
    coord.on_tick(0, _tick(4.1, [1.2, 1.2, 1.0], "TRACK"))
    coord.on_tick(1, _tick(4.1, [1.2, 1.2, 1.5], "TRACK"))
    assert sups[1].lands == []
    coord.on_tick(0, _tick(4.2, [0.5, 0.0, 1.0], "TRACK"))  # it has moved on
    coord.on_tick(1, _tick(4.2, [1.2, 1.2, 1.5], "TRACK"))
    assert sups[1].lands == ["fleet_fault"]


def test_a_stalled_loops_hold_is_level_for_a_drone_with_another_below_it(tmp_path):
    from cfknode.app.fleet.landing_order import StallHold

    class _Radio:
        def __init__(self):
            self.levels = []

        def hold_level(self, thrust):
            self.levels.append(thrust)

    cfg = stack_cfg(tmp_path, size=2, **{"trajectory.duration": 10.0})
    names, _, refs = drone_configs(cfg)
    radios = [_Radio(), _Radio()]
    coord = FleetCoordinator(cfg, names, [_Sup(), _Sup()], refs, _Log(), [StallHold(r, 38000) for r in radios])
    coord.on_tick(0, _tick(4.0, [0.5, 0.0, 1.0], "TRACK"))
    coord.on_tick(1, _tick(4.0, [0.5, 0.1, 1.5], "TRACK"))  # right above cf1
    coord.on_tick(0, _tick(4.1, [0.5, 0.0, 1.0], "TRACK"))
    assert radios[1].levels == [38000] and radios[0].levels == []  # told once; the lowest descends
    coord.on_tick(1, _tick(4.1, [1.2, 1.2, 1.5], "TRACK"))  # clear of it: the descending hold again
    assert radios[1].levels == [38000, None]


def test_a_ray_actors_gate_judges_by_the_fleet_the_driver_last_told_it(tmp_path):
    from cfknode.app.fleet.landing_order import StackGeometry, ViewGate

    cfg = stack_cfg(tmp_path, size=2)
    notes = []
    gate = ViewGate(StackGeometry.from_config(cfg), 1, notes.append)
    here = np.array([0.5, 0.0, 1.5])
    assert not gate.blocked(here)  # nothing told yet: nothing known below
    gate.update([(0.5, 0.0, 1.0), (0.5, 0.0, 1.5)], ["TRACK", "TRACK"], {})
    spot, move_s = gate.spot(here)
    assert np.hypot(*(spot[:2] - [0.5, 0.0])) >= LANDING_CLEARANCE * cfg.fleet.min_separation - 1e-9
    assert spot[2] == 1.5 and move_s > 0 and gate.spot_now == tuple(spot)
    assert gate.blocked(here) and gate.blocked(here) and len(notes) == 1  # waits, said once
    gate.update([(0.5, 0.0, 0.0), (0.5, 0.0, 1.5)], ["LANDED", "TRACK"], {})
    assert not gate.blocked(here)  # the one below is down


def test_a_ray_actor_that_ran_ahead_begins_no_descent_until_the_fleets_view_catches_up(tmp_path):
    """Each actor's lockstep clock runs at its own pace: the driver's word on the drone below may come from
    before it took off (no position yet, still in pre-flight), which would send the upper drone straight down
    onto it."""
    from cfknode.app.fleet.landing_order import VIEW_LAG_S, StackGeometry, ViewGate

    cfg = stack_cfg(tmp_path, size=2)
    notes = []
    gate = ViewGate(StackGeometry.from_config(cfg), 1, notes.append)
    here = np.array([0.5, 0.0, 1.5])
    gate.at(3.0)  # the actor's own flight time
    assert gate.blocked(here)  # no view of the fleet yet
    gate.update([None, tuple(here)], ["PREFLIGHT", "TRACK"], {}, [0.01, 3.0])  # cf1 as it was before take-off
    spot, move_s = gate.spot(here)
    assert move_s == 0.0 and np.allclose(spot, here)  # nothing known below: a straight descent ...
    assert gate.blocked(here)  # ... which it does not begin on a view 3 s old
    assert not gate.blocked(here, descending=True)  # on the way down only a flying drone below stops it
    gate.update([(0.5, 0.0, 1.0), tuple(here)], ["TRACK", "TRACK"], {}, [3.0 - VIEW_LAG_S + 0.01, 3.0])
    spot, move_s = gate.spot(here)
    assert move_s > 0 and np.hypot(*(spot[:2] - [0.5, 0.0])) >= LANDING_CLEARANCE * cfg.fleet.min_separation - 1e-9
    assert gate.blocked(here)  # caught up: cf1 flies below it
    gate.update([(0.5, 0.0, 0.0), tuple(here)], ["LANDED", "TRACK"], {}, [float("inf"), 3.0])
    assert not gate.blocked(here)  # cf1 is down and its flight has ended: it holds nobody back
    assert notes == ["waits to land: no view of the fleet yet", "waits to land: a flying drone is below it"]


def test_a_lockstep_actor_that_ran_ahead_holds_its_loop_until_the_view_catches_up(tmp_path):
    """Hovering in flight time would not do: the actor's own clock runs on while it hovers. Its loop (and
    with it its simulator) waits instead, for the view to come within VIEW_LAG_S or to stand still."""
    from cfknode.app.fleet.landing_order import SILENT_S, VIEW_LAG_S, StackGeometry, ViewGate

    wall = [0.0]
    gate = ViewGate(StackGeometry.from_config(stack_cfg(tmp_path, size=2)), 1, wall=lambda: wall[0])
    here = np.array([0.5, 0.0, 1.5])
    gate.at(3.0)
    gate.update([(0.5, 0.0, 1.0), tuple(here)], ["TRACK", "TRACK"], {}, [1.0, 3.0])
    gate.catch_up()  # not waiting to descend: returns at once
    assert gate.caught_up_s == 0.0
    assert gate.blocked(here)  # a view 2 s behind
    released = threading.Event()
    loop = threading.Thread(target=lambda: (gate.catch_up(), released.set()), daemon=True)
    loop.start()
    assert not released.wait(0.2)  # holds the loop
    gate.update([(0.5, 0.0, 1.0), tuple(here)], ["TRACK", "TRACK"], {}, [3.0 - VIEW_LAG_S, 3.0])
    assert released.wait(10.0)  # a hang guard
    loop.join(10.0)
    # A drone whose time stands still (started late, or hung until the driver has its ending): it does not
    # hold the loop for ever; the drone hovers on in flight time.
    gate.at(6.0)
    assert gate.blocked(here)
    wall[0] += SILENT_S
    gate.catch_up()
    assert gate.blocked(here)  # still not descending on a view 3 s old


# --- in flight ----------------------------------------------------------------------------------


def test_a_fault_below_never_lands_the_upper_drone_onto_the_lower(tmp_path):
    """cf1 loses the mocap under cf2 and lands; land_all lands cf2, which glides clear first."""
    cfg = stack_cfg(tmp_path, size=2, **{"trajectory.duration": 3.0, "sim.aero": "ideal", "sim.downwash.enabled": True,
                                        "faults.mocap_outages": [{"t": 2.5, "duration": 1.0}]})
    result = run_fleet(cfg)
    causes = [d.outcome.cause for d in result.drones]
    assert causes == ["mocap_lost", "fleet_fault"]
    assert all(d.outcome.state.value in ("LANDED", "EMERGENCY") for d in result.drones)
    # Closest true distance while either flew: never under the minimum separation.
    assert result.min_separation_m >= cfg.fleet.min_separation
    cf2 = result.drones[1].record
    end = cf2.p[cf2.ticks - 1]
    assert np.hypot(*(end[:2] - result.drones[0].record.p[result.drones[0].record.ticks - 1][:2])) >= 0.3


def test_a_pair_that_parted_and_comes_close_again_is_reported_again():
    from cfknode.safety.separation import REARM_M, SeparationWatch

    watch = SeparationWatch(["a", "b"], 0.3)
    both = [True, True]
    watch.update(0, (0, 0, 1.0), both)
    assert watch.update(1, (0, 0, 1.25), both) == [(0, 1, pytest.approx(0.25))]
    assert watch.update(1, (0, 0, 1.32), both) == []  # jitter around the minimum: not parted
    assert watch.update(1, (0, 0, 1.2), both) == []
    watch.update(1, (0.3 + REARM_M + 0.01, 0, 1.0), both)  # parted (a glide clear)
    assert watch.update(1, (0.1, 0, 1.0), both) == [(0, 1, pytest.approx(0.1))]  # e.g. while landing


# --- stop paths: every landing bottom-up ----------------------------------------------------------


class _StopAt:
    """Stands in for the fleet's dashboard (``run_fleet(dashboard=...)``): its one tick observer, on
    cf1, sends the stop once the flight time reaches ``t``, as an operator would, mid-pattern."""

    def __init__(self, t: float, send) -> None:
        self.t, self.send, self.sent = t, send, False

    def observers(self, i, drone, reference, controller, supervisor, coordinator):
        stop = self

        class _Tap:
            def on_tick(self, info):
                if i == 0 and not stop.sent and info.t >= stop.t:
                    stop.sent = True
                    stop.send()

        return [_Tap()]


def _airborne_min_separation(result, ground_z: float = 0.0) -> float:
    """The closest true distance between two drones at ticks where either is airborne (more than 5 cm
    up); a drone whose loop has ended stays where it was last recorded (landed: motors off)."""
    recs = [d.record for d in result.drones]
    n = max(r.ticks for r in recs)
    held = [np.concatenate([r.p[:r.ticks], np.repeat(r.p[r.ticks - 1:r.ticks], n - r.ticks, axis=0)]) for r in recs]
    best = np.inf
    for a in range(len(held)):
        for b in range(a + 1, len(held)):
            air = (held[a][:, 2] > ground_z + 0.05) | (held[b][:, 2] > ground_z + 0.05)
            if air.any():
                best = min(best, float(np.linalg.norm(held[a] - held[b], axis=1)[air].min()))
    return best


@pytest.mark.parametrize("stop", ["sigint", "estop_all_land"])
def test_a_stop_mid_flight_lands_a_stack_of_three_without_one_drone_passing_another(tmp_path, stop):
    """A stack of three (0.7, 1.2, 1.7 m, one column) under downwash, stopped mid-pattern by Ctrl-C
    or by ``cfknode estop --all --land``: each lands clear of those below (it glides aside first)."""
    import os
    import signal
    import threading

    from cfknode.app.commands.estop_all import estop_all

    cfg = stack_cfg(tmp_path, **{"trajectory.height": 0.7, "trajectory.duration": 3.0, "sim.aero": "ideal", "sim.downwash.enabled": True})
    if stop == "sigint":
        send = lambda: os.kill(os.getpid(), signal.SIGINT)  # noqa: E731
        cause = "sigint"
    else:
        codes = []
        send = lambda: threading.Thread(target=lambda: codes.append(  # noqa: E731
            estop_all(tmp_path / "estop", "land", timeout=10.0)), daemon=True).start()
        cause = "estop_land"
    stopper = _StopAt(3.0, send)
    result = run_fleet(cfg, dashboard=stopper)
    assert stopper.sent
    for d in result.drones:
        assert d.outcome.state.value == "LANDED", d.outcome.message
        assert d.outcome.cause in (cause, "fleet_fault"), d.outcome.message
        assert d.summary.extra["vehicle_after_shutdown"]["on_ground"]
    # Before they landed bottom-up, the upper two came down onto cf1's column: 5 cm apart at touchdown.
    assert _airborne_min_separation(result) >= cfg.fleet.min_separation
    assert result.min_separation_m >= cfg.fleet.min_separation  # the summary's closest approach says the same
    ends = [d.record.p[d.record.ticks - 1] for d in result.drones]
    for a in range(3):
        for b in range(a + 1, 3):
            assert np.hypot(*(ends[a][:2] - ends[b][:2])) >= cfg.fleet.min_separation


class _Gate:
    """A landing gate with a drone below until ``free_at``, and a spot that moves once."""

    def __init__(self, spots, free_at):
        self.spots, self.free_at, self.now = list(spots), free_at, 0.0
        self.asked: list[bool] = []  # each blocked() call: asked on the way down?

    def spot(self, p):
        return np.array(self.spots.pop(0) if self.spots else p, dtype=float), 1.0

    def blocked(self, p, descending=False):
        self.asked.append(descending)
        return self.now < self.free_at


def test_an_ordered_landing_glides_waits_for_the_drone_below_then_descends():
    from cfknode.safety.ordered_landing import OrderedLanding

    gate = _Gate([[0.95, 0.0, 1.5]], free_at=3.0)
    landing = OrderedLanding(gate, [0.5, 0.0, 1.5], 0.0, 0.0, 0.5)
    for t in np.arange(0.0, 3.0, 0.1):
        gate.now = t
        landing.advance(t)
        p = landing.sample(np.array([t])).p[0]
        assert p[2] == pytest.approx(1.5) and landing.t_end == np.inf  # at its height until cleared
    assert np.allclose(landing.sample(np.array([2.9])).p[0], [0.95, 0.0, 1.5])  # at its spot, waiting
    gate.now = 3.0
    landing.advance(3.0)
    assert landing.phase == "descend" and landing.t_end == pytest.approx(3.0 + 1.875 * 1.5 / 0.5)
    assert not any(gate.asked)  # every question so far was whether to begin the descent
    end = landing.sample(np.array([landing.t_end])).p[0]
    assert np.allclose(end, [0.95, 0.0, 0.0])
    gate.free_at = 10.0  # a flying drone comes under it on the way down: it hovers where it got to
    gate.now = 4.0
    landing.advance(4.0)
    assert landing.phase == "glide" and landing.t_end == np.inf and gate.asked[-1]  # asked on the way down
    assert 0.0 < landing.sample(np.array([5.0])).p[0][2] < 1.5
