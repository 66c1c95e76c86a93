"""The live dashboard: frames, layout, the key reader in a real pseudo-terminal, the task beside a loop."""

import argparse
import asyncio
import io
import math
import os
import pty
import re
import sys
import termios
import time

import numpy as np
import pexpect
import pytest
from rich.console import Console

from cfknode.app.ui.dashboard import (
    DashboardStarter,
    FrameMeter,
    KeyReader,
    Pace,
    render_frame,
    run_dashboard,
    should_show_dashboard,
    with_dashboard,
)
from cfknode.app.ui.status import FlightStatus, ModelEntry

PANELS = ("Supervisor", "Tracking", "Loop & MPC", "MPC", "Model queue", "Trainer", "Mocap", "Radio", "Battery",
          "Geofence", "Keys")
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def busy_status() -> FlightStatus:
    status = FlightStatus(400.0, title="circle r=0.5 m · mpc (rti)")
    for k in range(500):
        status.record_tick(k / 400, k / 3000, 2e-4, 1.5e-4, k == 7, "mpc", np.array([0.5, 0.01, 1.0]),
                           np.array([0.5, 0.0, 1.0]))
    status.supervisor_state, status.battery_v, status.geofence_margin_m = "TRACK", 4.05, 0.82
    status.models = (ModelEntry(2, 0.5, math.exp(-1), 0.031), ModelEntry(3, 1.0, 1.0, 0.021))
    status.model_version, status.model_swaps, status.model_rejects = 3, 3, 1
    status.trainer_state, status.trainer_last_loss, status.windows_accepted = "training", 1.2e-3, 12
    status.mocap_rate_hz, status.setpoints_sent = 100.0, 2000
    status.add_event(0.9, "warning", "model 4 reject: validation error worse")
    return status


def draw(status: FlightStatus, width: int, height: int) -> list[str]:
    console = Console(width=width, height=height, color_system=None, force_terminal=False)
    with console.capture() as cap:
        console.print(render_frame(status, wall_now=500 / 3000))
    return cap.get().splitlines()


@pytest.mark.parametrize(("width", "height"), [(120, 40), (100, 30), (80, 24)])
def test_frame_shows_every_panel_and_fits_the_screen(width, height):
    lines = draw(busy_status(), width, height)
    text = "\n".join(lines)
    for name in PANELS:
        assert name in text, name
    assert len(lines) <= height
    assert all(len(line) <= width for line in lines)
    for value in ("TRACK", "4.05 V", "+0.82 m", "*v3", "training", "12 ok", "100 Hz", "2000 setpoints",
                  "400 Hz", "missed   1 of 500", "|e| 10.0 mm"):
        assert value in text, value


@pytest.mark.parametrize(("width", "height"), [(120, 40), (100, 30), (80, 24)])
def test_frame_shows_the_fast_layer_as_flown(width, height):
    from cfknode.flight.adaptation import AdaptationEstimate, applied_estimate

    status = busy_status()
    estimate = AdaptationEstimate(np.array([0.21, -0.004, 0.012]), 1.31, np.ones(3), stepping=True)
    status.layer = applied_estimate(estimate, np.array([True, False, True]))
    lines = draw(status, width, height)
    text = "\n".join(lines)
    assert len(lines) <= height and all(len(line) <= width for line in lines)
    if height < 30:  # a short screen: the panel gives way after the event list, the key help stays
        assert "Fast layer" not in text and "Keys" in text and "Model queue" in text
        return
    for value in ("Fast layer", "1.310 x nominal", "+0.210 +0.000 +0.012", "acts     x z", "tracking a step"):
        assert value in text, value
    status.layer = applied_estimate(estimate, np.zeros(3, dtype=bool))
    assert "none: the model alone" in "\n".join(draw(status, 120, 40))
    assert "Fast layer" not in "\n".join(draw(busy_status(), 120, 40))  # no layer, no panel


def test_event_panel_shows_on_a_tall_screen_and_gives_way_on_a_short_one():
    assert "validation error worse" in "\n".join(draw(busy_status(), 120, 40))
    assert "Events" not in "\n".join(draw(busy_status(), 80, 20))


def test_empty_status_renders_as_not_available():
    text = "\n".join(draw(FlightStatus(), 100, 30))
    assert "n/a" in text and "nominal model, no networks" in text and "off" in text


def test_should_show_dashboard(monkeypatch):
    class Tty(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setenv("TERM", "xterm-256color")
    args = argparse.Namespace(headless=False)
    assert should_show_dashboard(args, Tty())
    assert not should_show_dashboard(args, io.StringIO())  # piped output
    assert not should_show_dashboard(argparse.Namespace(headless=True), Tty())
    assert not should_show_dashboard(args, Tty(), enabled=False)
    monkeypatch.setenv("TERM", "dumb")
    assert not should_show_dashboard(args, Tty())


async def _lockstep_flight(status: FlightStatus, meter: FrameMeter, frames_wanted: int) -> list[int]:
    """A loop that yields only sleep(0) between ticks, as in lockstep; ticks seen at each new frame."""
    ticks_at_frame: list[int] = []
    k = 0
    deadline = time.monotonic() + 20.0
    while len(ticks_at_frame) < frames_wanted and time.monotonic() < deadline:
        start = time.perf_counter()
        sum(i * i for i in range(300))  # a tick's worth of work
        status.record_tick(k / 400, start, time.perf_counter() - start, 0.0, False, "mpc", (0, 0, 1), (0, 0, 1))
        k += 1
        if len(meter.costs) > len(ticks_at_frame):
            ticks_at_frame.append(k)
        await asyncio.sleep(0)
    return ticks_at_frame


def test_dashboard_task_draws_between_lockstep_ticks():
    status = FlightStatus()
    meter = FrameMeter()
    out = io.StringIO()
    console = Console(file=out, width=100, height=30, force_terminal=True)

    async def main():
        stop = asyncio.Event()
        task = asyncio.create_task(run_dashboard(status, stop, console, pace=Pace(refresh_hz=20.0), meter=meter))
        ticks_at_frame = await _lockstep_flight(status, meter, frames_wanted=4)
        stop.set()
        return ticks_at_frame, await task

    ticks_at_frame, stats = asyncio.run(main())
    # The loop kept ticking between frames, and the dashboard kept drawing while it did.
    assert len(ticks_at_frame) == 4
    assert all(b > a for a, b in zip(ticks_at_frame, ticks_at_frame[1:]))
    assert stats.frames == len(meter.costs) >= 5  # 4 while flying, and the last one
    assert "Loop & MPC" in ANSI.sub("", out.getvalue())


def test_costly_frames_are_spaced_out_to_stay_within_the_budget():
    status = FlightStatus()
    polls: list[float] = []

    def costly(_status) -> None:  # a frame now costs at least 20 ms
        time.sleep(0.02)
        polls.append(time.perf_counter())
        if len(polls) == 2:
            stop.set()  # after the second frame, whatever the machine's load: the count does not race the clock

    status.add_poller(costly)
    console = Console(file=io.StringIO(), width=100, height=30, force_terminal=True)
    stop: asyncio.Event

    async def main():
        nonlocal stop
        stop = asyncio.Event()
        return await run_dashboard(status, stop, console, pace=Pace(refresh_hz=10.0, budget=0.05))

    stats = asyncio.run(main())
    # The first frame's cost is one-off (rich's caches) and sets nothing; the second's spaces the next frame
    # to 20 ms / 5 % = 0.4 s at least, against the refresh rate's 0.1 s.
    assert stats.frames == 2
    assert stats.period_s >= 0.02 / 0.05


def test_starter_runs_the_dashboard_beside_a_loop_it_does_not_own():
    status = FlightStatus()
    out = io.StringIO()
    starter = DashboardStarter(status, Console(file=out, width=100, height=30, force_terminal=True), refresh_hz=20.0)

    async def flight():  # stands for fly(parts), which calls its observers every tick
        k = 0
        while len(starter.meter.costs) < 3:
            status.record_tick(k / 400, time.perf_counter(), 1e-4, 0.0, False, "mpc", (0, 0, 1), (0, 0, 1))
            starter.on_tick(None)
            k += 1
            await asyncio.sleep(0.001)

    asyncio.run(flight())  # ending the event loop cancels the dashboard, which draws a last frame
    assert starter.stats.frames == 4
    assert "Tracking" in ANSI.sub("", out.getvalue())


def test_with_dashboard_returns_the_flight_result_and_passes_its_error():
    console = Console(file=io.StringIO(), width=100, height=30, force_terminal=True)

    async def flight(fail: bool):
        await asyncio.sleep(0.05)
        if fail:
            raise RuntimeError("boom")
        return 42

    assert asyncio.run(with_dashboard(flight(False), FlightStatus(), console)) == 42
    with pytest.raises(RuntimeError, match="boom"):
        asyncio.run(with_dashboard(flight(True), FlightStatus(), console))


def test_key_reader_reports_keys_in_cbreak_and_restores_the_terminal():
    master, slave = pty.openpty()
    stream = os.fdopen(slave, "r")
    saved = termios.tcgetattr(slave)
    seen: list[str] = []
    modes_inside = []

    def on_key(name):
        if name == "x":
            raise ValueError("bad key")
        seen.append(name)

    async def main(fail: bool):
        with KeyReader(stream, on_key) as keys:
            assert keys.active
            modes_inside.append(termios.tcgetattr(slave)[3])
            os.write(master, b" qx\n")
            for _ in range(200):
                await asyncio.sleep(0.005)
                if len(seen) >= 3:
                    break
            if fail:
                raise KeyboardInterrupt
        return keys.error

    try:
        assert asyncio.run(main(False)) == "ValueError: bad key"
        assert seen == ["space", "q", "enter"]
        assert not modes_inside[0] & (termios.ECHO | termios.ICANON)  # cbreak while reading
        assert modes_inside[0] & termios.ISIG  # Ctrl-C still a signal
        assert termios.tcgetattr(slave) == saved
        with pytest.raises(KeyboardInterrupt):
            asyncio.run(main(True))
        assert termios.tcgetattr(slave) == saved
    finally:
        stream.close()
        os.close(master)


def test_key_reader_does_nothing_off_a_terminal():
    async def main():
        with KeyReader(io.StringIO(), lambda name: None) as keys:
            return keys.active

    assert asyncio.run(main()) is False


def _expect_panels(child: pexpect.spawn) -> None:
    for name in PANELS:
        child.expect_exact(name)


def test_demo_flight_draws_the_dashboard_in_a_pseudo_terminal(tmp_path):
    child = pexpect.spawn(
        sys.executable, ["-m", "cfknode.app.commands.dashboard_demo", "--demo", "--log-dir", str(tmp_path),
                         "--set", "trajectory.duration=5.0"],
        dimensions=(40, 120), encoding="utf-8", timeout=120, cwd=str(tmp_path), env={**os.environ, "TERM": "xterm"},
    )
    try:
        child.expect_exact("Supervisor")
        _expect_panels(child)
        assert not child.getecho()  # cbreak while the dashboard reads keys
        child.send("q")
        child.expect("key 'q' pressed: e-stop requested")
        child.expect(r"dashboard: (\d+) frames")
        assert int(child.match.group(1)) >= 3
        child.expect(r"demo flight: (\d+) ticks")
        child.expect(pexpect.EOF)
        assert child.getecho()  # the terminal is back in its normal mode
    finally:
        child.close()
    assert child.exitstatus == 0
    assert list(tmp_path.glob("*dashboard-demo*.mcap"))


def test_cfknode_fly_draws_the_dashboard_in_a_pseudo_terminal(tmp_path):
    from cfknode.app.commands import fly

    parser = argparse.ArgumentParser()
    fly.add_arguments(parser)
    if "--headless" not in parser.format_help():
        pytest.skip("cfknode fly has no dashboard wiring (--headless) yet")
    child = pexpect.spawn(
        sys.executable, ["-m", "cfknode", "fly", "--log-dir", str(tmp_path), "--duration", "6",
                         "--set", "trajectory.takeoff_duration=2.0", "--set", "trajectory.land_duration=2.0"],
        dimensions=(40, 120), encoding="utf-8", timeout=120, cwd=str(tmp_path), env={**os.environ, "TERM": "xterm"},
    )
    try:
        _expect_panels(child)
        child.expect_exact("TRACK")  # the supervisor's state reaches the dashboard
        assert not child.getecho()
        child.send("q")  # the e-stop key: the supervisor lands
        child.expect_exact("LAND")
        child.expect_exact("Flight summary")
        child.expect(r"cfknode: (landed: operator e-stop key \(q\)|flight complete: landed)")
        outcome = child.match.group(1)
        child.expect(pexpect.EOF)
        assert child.getecho()
    finally:
        child.close()
    # A lockstep flight is fast: the key may land the drone, or arrive once it is already landing.
    # An e-stop landing is safe but not a complete mission, so the exit status says which it was.
    assert child.exitstatus == (1 if outcome.startswith("landed: operator") else 0)
