"""The ``cfknode`` command line: ``cfknode fly`` (more subcommands arrive with later issues).

Bad input (a config key, a type, a missing file, a flag) ends with one line on stderr
naming what is wrong, and exit status 2.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any, Sequence

from cfknode import __version__
from cfknode.config import Config, ConfigError, load_config, parse_override

# CLI flag -> dotted config key. Flags are shortcuts; --set reaches every key.
FLY_FLAGS: dict[str, str] = {
    "backend": "backend",
    "traj": "trajectory.kind",
    "radius": "trajectory.radius",
    "speed": "trajectory.speed",
    "height": "trajectory.height",
    "duration": "trajectory.duration",
    "controller": "controller.kind",
    "solver": "controller.solver",
    "seed": "sim.seed",
    "uri": "radio.uri",
    "log_dir": "log.dir",
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cfknode", description="KNODE-MPC-Online flight stack for Crazyflie 2.x")
    parser.add_argument("--version", action="version", version=f"cfknode {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    fly = sub.add_parser("fly", help="fly a mission (default: simulated circle)")
    fly.add_argument("--config", help="YAML file overriding the defaults")
    fly.add_argument("--backend", choices=["sim", "cf"])
    fly.add_argument("--traj", choices=["hover", "circle", "figure8"], help="trajectory kind")
    fly.add_argument("--radius", type=float, help="pattern radius [m]")
    fly.add_argument("--speed", type=float, help="pattern speed [m/s]")
    fly.add_argument("--height", type=float, help="flight height [m]")
    fly.add_argument("--duration", type=float, help="time on the pattern [s]")
    fly.add_argument("--controller", choices=["mpc", "geometric"])
    fly.add_argument("--solver", choices=["rti", "ipopt"])
    fly.add_argument("--seed", type=int)
    fly.add_argument("--uri", help="radio URI (sim://0 in simulation)")
    fly.add_argument("--log-dir", dest="log_dir", help="directory for the flight log")
    fly.add_argument("--realtime", action="store_true", help="simulate against the wall clock instead of lockstep")
    fly.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override any config key")
    fly.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    fly.add_argument("--name", default=None, help="name hint for the log file")
    return parser


def fly_config(args: argparse.Namespace) -> Config:
    overrides: dict[str, Any] = {}
    for flag, key in FLY_FLAGS.items():
        value = getattr(args, flag)
        if value is not None:
            overrides[key] = value
    if args.realtime:
        overrides["sim.realtime"] = True
    for item in args.set:
        key, value = parse_override(item)
        overrides[key] = value
    return load_config(args.config, overrides)


def _cmd_fly(args: argparse.Namespace) -> int:
    cfg = fly_config(args)  # validate before importing the heavy parts
    from rich.console import Console

    from cfknode.flight.summary import render_summary, summary_to_json
    from cfknode.mission import MissionError, run_flight

    console = Console(stderr=args.json)
    t = cfg.trajectory
    if not args.json:
        console.print(
            f"[bold]cfknode fly[/]: {cfg.backend} backend, {t.kind} r={t.radius} m at {t.speed} m/s for "
            f"{t.duration} s, controller {cfg.controller.kind} ({cfg.controller.solver})"
        )
    try:
        result = run_flight(cfg, name_hint=args.name or t.kind)
    except MissionError as exc:
        print(f"cfknode: error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(summary_to_json(result.summary))
    else:
        render_summary(result.summary, console)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if args.command == "fly":
            return _cmd_fly(args)
    except ConfigError as exc:
        print(f"cfknode: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("cfknode: interrupted", file=sys.stderr)
        return 130
    return 2


if __name__ == "__main__":
    sys.exit(main())
