"""``cfknode fly --fleet N``: fly a simulated fleet and print one line per drone (docs/fleet.md)."""

from __future__ import annotations

import argparse
import json
import sys

from cfknode.app.config import Config


def run_fleet_command(cfg: Config, args: argparse.Namespace) -> int:
    """Exit status 0 when every drone flew its mission to the end and the log is complete, else 1."""
    from cfknode.app.fleet import run_fleet

    out = sys.stderr if args.json else sys.stdout
    t = cfg.trajectory
    ray = getattr(args, "executor", "local") == "ray"
    print(f"cfknode fly: fleet of {cfg.fleet.size} ({cfg.fleet.layout}), {t.kind} r={t.radius} m at {t.speed} m/s "
          f"for {t.duration} s, controller {cfg.controller.kind}, lockstep simulation"
          + (" (a Ray actor per drone)" if ray else ""), file=out)
    if ray:
        from cfknode.app.bench.executor import ExecutorSettings
        from cfknode.app.fleet_ray import run_fleet_ray
        from cfknode.app.mission import MissionError

        settings = ExecutorSettings.from_args(args, default_jobs=cfg.fleet.size)
        try:
            result = run_fleet_ray(cfg, settings, name_hint=args.name or f"fleet{cfg.fleet.size}")
        except MissionError as exc:  # the cluster could not be joined or could not place the drones
            print(f"cfknode: error: {exc}", file=sys.stderr)
            return 1
    else:
        result = run_fleet(cfg, name_hint=args.name or f"fleet{cfg.fleet.size}")
    if args.json:
        print(json.dumps({
            "log": result.log_path,
            "min_separation_m": result.min_separation_m,
            "radio_pps": result.radio_pps,
            "events": list(result.events),
            "drones": {d.name: {"uri": d.uri, "outcome": d.outcome.message, **d.summary.to_dict()}
                       for d in result.drones},
        }, default=float))
    for d in result.drones:
        s = d.summary
        print(f"{d.name} {d.uri}: MSE {s.mse:.2e} m^2, tick median {s.compute_median_ms:.2f} ms, "
              f"p99 {s.compute_p99_ms:.2f} ms: {d.outcome.message}", file=out)
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
