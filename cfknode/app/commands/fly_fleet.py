"""``cfknode fly --fleet N`` (a simulated fleet, with its live dashboard in a terminal) and ``cfknode fly
--robots cf1,cf2`` (robots from the robots file): fly them and print one line per drone (docs/fleet.md)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, Sequence

from cfknode.app.errors import UsageError
from cfknode.app.foxglove.live import live_view
from cfknode.app.config import Config


def run_fleet_command(cfg: Config, args: argparse.Namespace) -> int:
    """Exit status 0 when every drone flew its mission to the end and the log is complete, else 1."""
    from rich.console import Console

    from cfknode.app.fleet.flight import run_fleet
    from cfknode.safety.process_signals import ProcessSignals

    out = sys.stderr if args.json else sys.stdout
    t = cfg.trajectory
    ray = getattr(args, "executor", "local") == "ray"
    print(f"cfknode fly: fleet of {cfg.fleet.size} ({cfg.fleet.layout}), {t.kind} r={t.radius} m at {t.speed} m/s "
          f"for {t.duration} s, controller {cfg.controller.kind}{' + online learning' if cfg.online.enabled else ''}, "
          "lockstep simulation" + (" (a Ray actor per drone)" if ray else ""), file=out)
    if ray:
        if getattr(args, "foxglove", None) is not None:
            raise UsageError("--foxglove serves fleets flown here; a Ray fleet's drones fly on other nodes "
                             "(their logs carry the Foxglove channels: docs/foxglove.md)")
        from cfknode.app.bench.executor import ExecutorSettings
        from cfknode.app.fleet.ray_fleet import run_fleet_ray
        from cfknode.app.mission import MissionError

        settings = ExecutorSettings.from_args(args, default_jobs=cfg.fleet.size)
        try:  # the driver routes Ctrl-C, SIGTERM and SIGHUP to every actor (cfknode/app/fleet/ray_fleet.py)
            result = run_fleet_ray(cfg, settings, name_hint=args.name or f"fleet{cfg.fleet.size}")
        except MissionError as exc:  # the cluster could not be joined or could not place the drones
            print(f"cfknode: error: {exc}", file=sys.stderr)
            return 1
        return report(cfg, result, args)
    # SIGTERM and SIGHUP end a fleet as Ctrl-C does (every drone lands, then stops), as for one drone.
    dashboard = fleet_dashboard(cfg, args)
    with ProcessSignals() as signals, live_view(getattr(args, "foxglove", None), Console(stderr=True)) as live:
        result = run_fleet(cfg, name_hint=args.name or f"fleet{cfg.fleet.size}", on_coordinator=signals.route,
                           dashboard=dashboard, live=live)
    if dashboard is not None and dashboard.error is not None:
        print(f"cfknode: the dashboard failed ({dashboard.error}); the flight went on without it", file=sys.stderr)
    return report(cfg, result, args)

def run_robots_command(cfg: Config, names: Sequence[str], args: argparse.Namespace) -> int:
    """Fly the named robots together in real time; exit status as for ``--fleet``, and 1 when a
    robot could not be connected or failed its pre-flight checks."""
    from rich.console import Console

    from cfknode.app.fleet.robots import run_robot_fleet
    from cfknode.app.mission import MissionError
    from cfknode.safety.process_signals import ProcessSignals

    out = sys.stderr if args.json else sys.stdout
    t = cfg.trajectory
    print(f"cfknode fly: robots {', '.join(names)} ({cfg.fleet.layout}), {t.kind} r={t.radius} m at {t.speed} m/s "
          f"for {t.duration} s, controller {cfg.controller.kind}{' + online learning' if cfg.online.enabled else ''}, "
          "real time", file=out)
    dashboard = fleet_dashboard(cfg, args, len(names))
    try:  # Ctrl-C, SIGTERM and SIGHUP go to every robot's supervisor (cfknode/app/fleet/flight.py)
        with ProcessSignals() as signals, live_view(getattr(args, "foxglove", None), Console(stderr=True)) as live:
            result = run_robot_fleet(cfg, names, name_hint=args.name or "robots", console=Console(stderr=True),
                                     on_coordinator=signals.route, dashboard=dashboard, live=live)
    except MissionError as exc:
        print(f"cfknode: error: {exc}", file=sys.stderr)
        return 1
    return report(cfg, result, args)


def report(cfg: Config, result: Any, args: argparse.Namespace) -> int:
    """Print a fleet's result (one line per drone, the fleet's events, closest approach, radios)."""
    from cfknode.app.ui.summary import drone_row

    out = sys.stderr if args.json else sys.stdout
    if args.json:
        print(json.dumps({
            "log": result.log_path,
            "min_separation_m": result.min_separation_m,
            "radio_pps": result.radio_pps,
            "events": list(result.events),
            "drones": {d.name: {"uri": d.uri, "outcome": d.outcome.message, **d.summary.to_dict()}
                       for d in result.drones},
        }, default=float))
    verbose = getattr(args, "verbose", False)
    for d in result.drones:  # one row each; the URI only with --verbose, so a row fits 80 columns
        s = d.summary
        print(drone_row(f"{d.name} {d.uri}" if verbose else d.name, s, d.outcome.message), file=out)
        for path in s.extra.get("logs", ()):  # --executor ray: each drone's own logs, on its node
            print(f"{d.name} log {path} (node {str(s.extra.get('ray_node', ''))[:12]})", file=out)
    for event in result.events:
        print(f"fleet: {event}", file=out)
    radios = ", ".join(f"{r} {pps:g}/s" for r, pps in result.radio_pps.items())
    print(f"closest approach {result.min_separation_m:.3f} m (minimum {cfg.fleet.min_separation:g} m); "
          f"radios: {radios}; log {result.log_path}", file=out)
    if result.log_incomplete is not None:
        print(f"cfknode: the flight log is {result.log_incomplete}", file=sys.stderr)
    return 0 if result.complete and result.log_incomplete is None else 1


def fleet_dashboard(cfg: Config, args: argparse.Namespace, size: int | None = None) -> Any:
    """The fleet's live view when the single flight would show its dashboard (a terminal, not
    ``--headless``, ``dashboard.enabled``), on the same stream (stderr with ``--json``); else None."""
    from rich.console import Console

    from cfknode.app.ui.dashboard import should_show_dashboard
    from cfknode.app.ui.fleet_dashboard import FleetDashboard, FleetStatus

    console = Console(stderr=args.json)
    if not should_show_dashboard(args, console.file, cfg.dashboard.enabled):
        return None
    t, c = cfg.trajectory, cfg.controller
    title = f"{size or cfg.fleet.size} x {t.kind} r={t.radius} m ({cfg.fleet.layout}) - {c.kind} ({c.solver})"
    status = FleetStatus(title, cfg.fleet.min_separation, show_mass=c.adaptation != "none",
                         show_models=cfg.online.enabled)
    return FleetDashboard(console, status, cfg.dashboard.refresh_hz)
