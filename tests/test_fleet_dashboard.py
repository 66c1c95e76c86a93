"""The fleet dashboard: rows from tick sequences, the worst values on top, events, polling, wiring, when it shows."""

import argparse
import asyncio
import io
import math
from types import SimpleNamespace as NS

import numpy as np
import pytest
from rich.console import Console

from cfknode.app.commands.fly_fleet import fleet_dashboard
from cfknode.app.config import load_config
from cfknode.app.ui.fleet_dashboard import FleetDashboard, FleetStatus, TickHistogram, render_fleet_frame
from fakes import Est

WINDOW = (1.0, 4.0)


def feed(row, seconds, offset_m, compute_s, state=lambda t: "TRACK", version=lambda t: 0, rate=400.0):
    """Ticks with a constant y error of ``offset_m`` (the reference on the circle)."""
    for k in range(int(seconds * rate)):
        t = k / rate
        ref = np.array([0.5 * math.cos(t), 0.5 * math.sin(t), 1.0])
        row.on_tick(NS(t=t, est=Est(p=ref + [0.0, offset_m, 0.0], v=np.zeros(3)), ref_p=ref, compute_s=compute_s(k),
                       supervisor_state=state(t), model_version=version(t)))


class Supervisor:
    def __init__(self, cause="", battery=3.9, silence=0.0):
        self.cause, self.battery, self.silence = cause, battery, silence
        self.land_requests = []

    def snapshot(self):
        return NS(cause=self.cause, battery_v=self.battery, link_silence_s=self.silence)

    def request_land(self, reason, cause="operator"):
        self.land_requests.append(reason)


class Coordinator:
    def __init__(self):
        self.events = []
        self.watch = NS(closest=math.inf)


def draw(status, width=110, height=40):
    console = Console(width=width, height=height, color_system=None, force_terminal=False)
    with console.capture() as cap:
        console.print(render_fleet_frame(status, wall_now=0.0))
    return cap.get()


def row_of(text, name):
    return next(line for line in text.splitlines() if line.startswith(f"│ {name} "))


def three_drones():
    status = FleetStatus("3 x circle", min_separation=0.3, show_mass=True, show_models=True)
    coordinator = Coordinator()
    status.watch(coordinator)
    sups = [Supervisor(battery=3.91), Supervisor(battery=3.85), Supervisor(cause="battery", battery=3.2)]
    adapt = NS(adaptation=NS(estimate=NS(thrust_scale=1.27)))
    rows = [status.add_drone("cf1", "sim://0", WINDOW, sups[0], NS(adaptation=None), NS(stats=lambda: NS(
                link_lost=None, send_errors=0))),
            status.add_drone("cf2", "sim://1", WINDOW, sups[1], adapt, None),
            status.add_drone("cf3", "sim://2", WINDOW, sups[2], None, NS(stats=lambda: NS(
                link_lost="timeout", send_errors=3)))]
    # cf1 tracks 1 mm off with fast ticks; cf2 3 mm off, 2 % of its ticks slow and two models
    # swapped in; cf3 2 mm off until its supervisor lands it at 3 s.
    feed(rows[0], 5.0, 0.001, lambda k: 4e-4)
    feed(rows[1], 5.0, 0.003, lambda k: 0.02 if k % 50 == 0 else 5e-4, version=lambda t: int(t // 2))
    feed(rows[2], 5.0, 0.002, lambda k: 6e-4, state=lambda t: "TAKEOFF" if t < 0.5 else ("TRACK" if t < 3 else "LAND"))
    coordinator.events.append("3.000 s warning: cf3 ended its flight (battery); fleet.on_fault land_all")
    coordinator.watch.closest = 0.8543
    status.poll()
    return status, rows, sups


def test_each_drone_has_a_row_with_its_errors_tick_times_and_parts():
    status, rows, _ = three_drones()
    text = draw(status)
    one, two, three = row_of(text, "cf1"), row_of(text, "cf2"), row_of(text, "cf3")
    assert "sim://0" in one and "TRACK" in one and "sim://2" in three and "LAND" in three
    # Pattern MSE is the summary's (mean over the axes): a 1 mm offset on one axis is 1e-6 / 3 m^2.
    assert rows[0].pattern_mse_m2() == pytest.approx(1e-6 / 3, rel=1e-6)
    assert rows[1].pattern_rms_m() == pytest.approx(0.003, rel=1e-6)
    assert "3.3e-07" in one and "3.0e-06" in two
    assert one.split()[4:6] == ["1.0", "1.00"]  # error now, pattern RMS, mm
    # Tick median from the histogram is within its bin of the true 0.4 ms.
    assert float(one.split()[7]) == pytest.approx(0.4, rel=0.03)
    assert rows[1].hist.quantile_ms(0.99) == pytest.approx(20.0, rel=0.03)
    assert "1.27" in two and "n/a" in one.split()[9]  # mass factor: cf2 adapts, cf1 does not
    assert two.split()[10] == "2" and one.split()[10] == "0"  # models swapped in
    assert "3.91" in one and "3.20" in three
    assert "LOST" in three and one.rstrip(" │").endswith("ok")


def test_the_worst_values_and_drones_not_tracking_are_on_top():
    status, _, _ = three_drones()
    text = draw(status)
    top = text[: text.index("Drones")]
    assert "error now  3.0 mm  cf2" in top
    assert "tick p99   2" in top and "ms  cf2" in top  # cf2's slow ticks (about 20 ms)
    assert "closest    0.854 m  (minimum 0.3 m)" in top
    assert "not TRACK  cf3 LAND" in top and "cf1 " not in top.split("not TRACK")[1]


def test_events_show_the_fleets_decisions_and_landings_with_their_cause_not_the_routine_way_up():
    status, _, _ = three_drones()
    events = draw(status).split("Fleet events")[1]
    assert "3.00 s warning  cf3 ended its flight (battery); fleet.on_fault land_all" in events
    assert "cf3 TRACK -> LAND (battery)" in events
    assert "TAKEOFF" not in events


def test_a_closest_approach_under_the_minimum_and_no_drones_tracking_yet():
    status = FleetStatus(min_separation=0.3)
    status.add_drone("cf1", "sim://0")
    text = draw(status)
    assert "n/a" in row_of(text, "cf1") and "not TRACK  cf1 n/a" in text
    coordinator = Coordinator()
    coordinator.watch.closest = 0.21
    status.watch(coordinator)
    status.poll()
    assert "closest    0.210 m" in draw(status)


def test_many_drones_fit_a_small_screen_by_dropping_the_events():
    status = FleetStatus()
    for i in range(12):
        feed(status.add_drone(f"cf{i + 1}", f"sim://{i}"), 0.1, 0.001, lambda k: 4e-4)
    lines = draw(status, width=80, height=24).splitlines()
    assert len(lines) <= 24 and "Fleet events" not in "\n".join(lines) and "Keys" in lines[-1]


def test_a_poll_that_fails_is_shown_not_raised():
    status = FleetStatus()
    status.add_drone("cf1", "sim://0", supervisor=NS(snapshot=lambda: 1 / 0))
    status.poll()
    assert "ZeroDivisionError" in draw(status)


def test_the_histogram_quantiles_match_numpys_within_a_bin():
    rng = np.random.default_rng(3)
    samples = np.concatenate([rng.lognormal(np.log(4e-4), 0.3, 5000), rng.uniform(0.01, 0.05, 100)])
    hist = TickHistogram()
    for x in samples:
        hist.add(float(x))
    for q in (0.5, 0.9, 0.99):
        assert hist.quantile_ms(q) == pytest.approx(np.quantile(samples, q) * 1e3, rel=0.03)
    assert math.isnan(TickHistogram().quantile_ms(0.5))
    hist.add(0.0)  # a zero or huge time lands in an end bin, never out of range
    hist.add(1e3)
    assert hist.total == len(samples) + 2


def test_the_dashboard_watches_each_drone_draws_beside_the_loop_and_its_keys_land_everyone():
    out = io.StringIO()
    console = Console(file=out, width=110, height=40, color_system=None, force_terminal=True)
    dash = FleetDashboard(console, FleetStatus("test"), refresh_hz=20.0)
    sups = [Supervisor(), Supervisor()]
    coordinator = Coordinator()
    drones = [NS(name=f"cf{i + 1}", config=NS(radio=NS(uri=f"sim://{i}")),
                 radio=NS(stats=lambda: NS(link_lost=None, send_errors=0))) for i in range(2)]
    observers = [dash.observers(i, d, NS(pattern_window=WINDOW), NS(adaptation=None), s, coordinator)
                 for i, (d, s) in enumerate(zip(drones, sups))]
    assert len(observers[0]) == 2 and len(observers[1]) == 1  # the first drone also starts the refresher

    async def flight():
        for k in range(40):
            for obs in observers:
                for o in obs:
                    o.on_tick(NS(t=k / 400, est=Est(np.zeros(3), np.zeros(3)), ref_p=np.zeros(3), compute_s=3e-4,
                                 supervisor_state="TRACK", model_version=0))
            await asyncio.sleep(0.005)

    asyncio.run(flight())
    assert dash.error is None and dash.stats.frames >= 2
    text = out.getvalue()
    assert "cfknode fleet" in text and "cf2" in text and "sim://1" in text
    assert dash.status.drones[0].window == WINDOW
    dash._on_key("q")
    assert all(s.land_requests == ["operator e-stop key (q)"] for s in sups)


class Stream(io.StringIO):
    def __init__(self, tty):
        super().__init__()
        self._tty = tty

    def isatty(self):
        return self._tty


@pytest.mark.parametrize(("headless", "enabled", "tty", "shown"), [
    (False, True, True, True), (True, True, True, False), (False, False, True, False), (False, True, False, False)])
def test_the_fleet_shows_its_dashboard_when_a_single_flight_would(monkeypatch, headless, enabled, tty, shown):
    monkeypatch.setenv("TERM", "xterm")
    stream = Stream(tty)
    monkeypatch.setattr("sys.stdout", stream)
    cfg = load_config(None, {"fleet.size": 3, "dashboard.enabled": enabled, "controller.adaptation": "dob"})
    dash = fleet_dashboard(cfg, argparse.Namespace(json=False, headless=headless))
    assert (dash is not None) is shown
    if shown:
        assert dash.status.show_mass and not dash.status.show_models and dash.status.min_separation == 0.3
