"""A short simulated circle flown through ``run_flight`` with the live dashboard: a demo and a test.

``python -m cfknode.app.commands.dashboard_demo --demo`` (``--headless`` flies without the
dashboard). It sits above ``cfknode.app.mission``, which itself draws on ``cfknode.app.ui``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import numpy as np
from rich.console import Console

from cfknode.app.config import load_config, parse_override
from cfknode.app.mission import run_flight
from cfknode.app.ui.dashboard import DashboardStarter, should_show_dashboard
from cfknode.app.ui.status import FlightStatus

DEMO_OVERRIDES = {
    "trajectory.duration": 4.0,
    "trajectory.takeoff_duration": 2.0,
    "trajectory.settle_duration": 0.5,
    "trajectory.land_duration": 2.0,
    "trajectory.ramp_duration": 1.0,
}


def main(argv: Sequence[str] | None = None) -> int:
    """Fly a short simulated circle through ``cfknode.app.mission.run_flight`` with the dashboard.

    The status and a ``DashboardStarter`` are passed as tick observers, so it needs nothing
    of the mission beyond its ``observers`` argument. Prints one line of timings at the end.
    """
    parser = argparse.ArgumentParser(prog="python -m cfknode.app.commands.dashboard_demo", description=main.__doc__)
    parser.add_argument("--demo", action="store_true", required=True, help="fly the demo flight")
    parser.add_argument("--headless", action="store_true", help="fly without the dashboard")
    parser.add_argument("--log-dir", default="flights", help="directory for the flight log")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config key (every key: docs/configuration.md)")
    args = parser.parse_args(argv)
    cfg = load_config(overrides={**DEMO_OVERRIDES, "log.dir": args.log_dir, **dict(map(parse_override, args.set))})
    console = Console()
    t = cfg.trajectory
    status = FlightStatus(cfg.controller.rate_hz, title=f"{t.kind} r={t.radius} m · {cfg.controller.kind} "
                          f"({cfg.controller.solver}) · {'realtime' if cfg.sim.realtime else 'lockstep'} demo")

    def on_key(name: str) -> None:
        # The safety supervisor owns the action; the demo shows that the key arrived.
        status.add_event(status.t, "warning", f"key {name!r} pressed: e-stop requested")

    starter = None
    if should_show_dashboard(args, console.file, cfg.dashboard.enabled):
        starter = DashboardStarter(status, console, on_key, cfg.dashboard.refresh_hz)
    result = run_flight(cfg, name_hint="dashboard-demo", observers=[status, *([starter] if starter else [])])
    if starter is not None:
        dash = starter.stats
        console.print(f"dashboard: {dash.frames} frames, {dash.median_frame_ms:.2f} ms median, "
                      f"{dash.max_frame_ms:.2f} ms max, every {dash.period_s * 1e3:.0f} ms", highlight=False)
    record = result.record
    compute_ms = record.compute_s * 1e3
    duration = float(record.t[-1] - record.t[0]) if record.ticks else 0.0
    console.print(
        f"demo flight: {record.ticks} ticks, speed {duration / record.wall_time:.2f}x real time, "
        f"tick median {np.median(compute_ms):.3f} ms, p99 {np.percentile(compute_ms, 99):.3f} ms, "
        f"missed {int(record.missed.sum())}, log {result.summary.log_path}",
        soft_wrap=True,
        highlight=False,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
