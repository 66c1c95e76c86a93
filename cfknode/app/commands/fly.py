"""``cfknode fly``: fly a mission (by default the simulated 0.5 m circle)."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

from cfknode.app.errors import UsageError
from cfknode.app.config import Config, load_config, parse_override

HELP = "fly a mission (default: the simulated 0.5 m circle)"
NAME_MAX = 64  # the log file adds a 16-character timestamp; file names end at 255 bytes
_NAME = re.compile(rf"[A-Za-z0-9._-]{{1,{NAME_MAX}}}")

# CLI flag -> dotted config key. Flags are shortcuts; --set reaches every key.
FLAGS: dict[str, str] = {
    "backend": "backend",
    "traj": "trajectory.kind",
    "radius": "trajectory.radius",
    "speed": "trajectory.speed",
    "height": "trajectory.height",
    "duration": "trajectory.duration",
    "controller": "controller.kind",
    "model": "controller.model",
    "solver": "controller.solver",
    "seed": "sim.seed",
    "uri": "radio.uri",
    "log_dir": "log.dir",
    "robot": "hardware.robot",
    "robots_file": "hardware.robots_file",
    "mocap": "hardware.mocap_type",
    "mocap_host": "hardware.mocap_host",
    "fleet": "fleet.size",
    "fleet_layout": "fleet.layout",
}


def add_config_arguments(p: argparse.ArgumentParser) -> None:
    """The options every command that builds a flight configuration shares."""
    p.add_argument("--config", help="YAML file overriding the defaults")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config key (every key: docs/configuration.md)")


def add_hardware_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--backend", choices=["sim", "cf"])
    p.add_argument("--robot", help="robot in the robots file (also the mocap rigid-body name)")
    p.add_argument("--robots", metavar="NAMES",
                   help="robots of the robots file to fly together, comma-separated (cf1,cf2,cf3; one name is "
                        "--robot NAME); docs/fleet.md")
    p.add_argument("--robots-file", dest="robots_file", metavar="PATH",
                   help="Crazyswarm2-style robots YAML (default: the packaged example)")
    p.add_argument("--mocap", choices=["vicon", "optitrack", "qualisys", "vrpn", "mock"], help="motion capture type")
    p.add_argument("--mocap-host", dest="mocap_host", help="motion capture host name or address")
    p.add_argument("--force", action="store_true", help="fly despite failed pre-flight checks (logged)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_config_arguments(p)
    add_hardware_arguments(p)
    p.add_argument("--traj", choices=["hover", "circle", "figure8", "line", "vertical"], help="trajectory kind")
    p.add_argument("--radius", type=float, help="pattern radius [m]")
    p.add_argument("--speed", type=float, help="pattern speed [m/s]")
    p.add_argument("--height", type=float, help="flight height [m]")
    p.add_argument("--duration", type=float, help="time on the pattern [s]")
    p.add_argument("--controller", choices=["mpc", "knode-mpc", "geometric"])
    p.add_argument("--model", help="KNODE model file: fly KNODE-MPC with it")
    p.add_argument("--solver", choices=["rti", "ipopt"])
    p.add_argument("--seed", type=int)
    p.add_argument("--uri", help="radio URI (sim://0 in simulation)")
    p.add_argument("--log-dir", dest="log_dir", help="directory for the flight log")
    p.add_argument("--realtime", action="store_true", help="simulate against the wall clock instead of lockstep")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.add_argument("--headless", action="store_true", help="fly without the live dashboard")
    p.add_argument("--online", action="store_true", help="learn the KNODE model in flight (config section online)")
    p.add_argument("--foxglove", nargs="?", type=int, const=8765, default=None, metavar="PORT",
                   help="serve the flight live to Foxglove on ws://127.0.0.1:PORT (default 8765; docs/foxglove.md)")
    p.add_argument("--paper-lockstep", dest="paper_lockstep", action="store_true",
                   help="online learning as the paper's code does it: the simulation waits for every model "
                        "(for reproduction only)")
    p.add_argument("--fleet", type=int, metavar="N", help="fly N simulated drones in one flight (docs/fleet.md)")
    p.add_argument("--fleet-layout", dest="fleet_layout", choices=["ring", "stack", "crossing"],
                   help="fleet: evenly spaced on the circle (ring), stacked heights (stack), or one hovering over "
                        "the other's line (crossing)")
    p.add_argument("--executor", choices=["local", "ray"], default="local",
                   help="fleet: local flies every drone in this process (default); ray makes each drone a Ray actor "
                        "on the node with its radio (docs/fleet-ray.md)")
    p.add_argument("--address", default=None,
                   help="with --executor ray: the Ray cluster (default: $RAY_ADDRESS, else a local Ray for the flight)")
    p.add_argument("--name", default=None,
                   help=f"name hint for the log file (up to {NAME_MAX} of A-Z a-z 0-9 . _ -)")


def robots_argument(args: argparse.Namespace) -> tuple[str, ...]:
    """The robot names of ``--robots``, with ``args.robot`` and ``args.robots_file`` settled.

    ``--robots`` once named the robots file: a value that is an existing file or ends in
    .yaml/.yml is still taken as the file, with a one-line deprecation warning on stderr."""
    value = getattr(args, "robots", None)
    if value is None:
        return ()
    if Path(value).is_file() or value.lower().endswith((".yaml", ".yml")):
        if getattr(args, "robots_file", None) is not None:
            raise UsageError(f"--robots {value} is a robots file, and --robots-file is given too: give one")
        print(f"cfknode: warning: --robots FILE is deprecated, use --robots-file {value} "
              "(--robots now names the robots to fly)", file=sys.stderr)
        args.robots_file = value
        return ()
    names = tuple(n.strip() for n in value.split(","))
    if not all(names):
        raise UsageError(f"--robots takes robot names separated by commas (cf1,cf2), got {value!r}")
    if len(names) == 1:
        if getattr(args, "robot", None) not in (None, names[0]):
            raise UsageError(f"--robot {args.robot} and --robots {names[0]} name different robots: give one")
        args.robot = names[0]
    elif getattr(args, "robot", None) is not None:
        raise UsageError("--robot flies one robot and --robots several: give one")
    return names


def config_from_args(args: argparse.Namespace, flags: dict[str, str] = FLAGS) -> Config:
    names = robots_argument(args)
    args.robot_names = names
    overrides: dict[str, Any] = {}
    if len(names) > 1:
        if getattr(args, "backend", None) == "sim":
            raise UsageError("--robots flies robots from the robots file (backend cf); --fleet N flies a "
                             "simulated fleet")
        overrides["backend"] = "cf"
    for flag, key in flags.items():
        value = getattr(args, flag, None)
        if value is not None:
            overrides[key] = value
    if getattr(args, "realtime", False):
        overrides["sim.realtime"] = True
    if getattr(args, "force", False):
        overrides["hardware.force"] = True
    if getattr(args, "online", False) or getattr(args, "paper_lockstep", False):
        overrides["online.enabled"] = True
    if getattr(args, "paper_lockstep", False):
        overrides["online.paper_lockstep"] = True
    for item in args.set:
        key, value = parse_override(item)
        overrides[key] = value
    return load_config(args.config, overrides)


def run(args: argparse.Namespace) -> int:
    if args.name is not None and not _NAME.fullmatch(args.name):
        shown = args.name if len(args.name) <= 24 else args.name[:24] + "..."
        raise UsageError(f"--name must be 1 to {NAME_MAX} of the characters A-Z a-z 0-9 . _ - "
                         f"(it names the log file), got {shown!r} ({len(args.name)} characters)")
    cfg = config_from_args(args)  # validate before importing the heavy parts
    if getattr(args, "address", None) is not None and getattr(args, "executor", "local") != "ray":
        raise UsageError("--address needs --executor ray")
    if getattr(args, "executor", "local") == "ray" and cfg.fleet.size < 2:
        raise UsageError("--executor ray flies a fleet (--fleet N, N >= 2); a single flight runs here")
    if len(args.robot_names) > 1:
        from cfknode.app.commands.fly_fleet import run_robots_command

        return run_robots_command(cfg, args.robot_names, args)
    if cfg.fleet.size >= 2:
        from cfknode.app.commands.fly_fleet import run_fleet_command

        return run_fleet_command(cfg, args)
    from rich.console import Console

    from cfknode.app.ui.dashboard import should_show_dashboard
    from cfknode.app.ui.summary import render, summary_to_json
    from cfknode.app.mission import MissionError, run_flight
    from cfknode.safety.process_signals import ProcessSignals

    console = Console(stderr=args.json)
    t = cfg.trajectory
    if not args.json:
        # One line within 80 columns, as the summary below it.
        console.print(
            f"[bold]cfknode fly[/]: {cfg.backend}, {t.kind} r={t.radius} m at {t.speed} m/s for "
            f"{t.duration} s, {cfg.controller.kind} ({cfg.controller.solver})"
        )
    show = should_show_dashboard(args, console.file, cfg.dashboard.enabled)
    # SIGTERM and SIGHUP end a flight as Ctrl-C does (land, then stop), never the process at once.
    try:
        from cfknode.app.foxglove.live import live_view

        with ProcessSignals() as signals, live_view(getattr(args, "foxglove", None), console) as live:
            result = run_flight(cfg, name_hint=args.name or t.kind, dashboard=console if show else None,
                                on_supervisor=signals.route, live=live)
    except MissionError as exc:
        print(f"cfknode: error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(summary_to_json(result.summary))
    else:  # by default the rows a person reads at a glance; --verbose every row
        render(result.summary, console, verbose=getattr(args, "verbose", False))
    # The one line that says how the flight ended (stderr with --json, so stdout stays JSON).
    print(f"cfknode: {result.outcome.message}", file=sys.stderr if args.json else sys.stdout)
    for error in result.outcome.errors:  # the tracebacks are in the log, never on the terminal
        print(f"cfknode: {error}; traceback in {result.summary.log_path} (/events)", file=sys.stderr)
    # 0 only for a mission flown to the end, fully logged and without an internal error; a
    # watchdog landing, a stop signal, a stop, a refusal or a log that stopped writing is 1.
    complete = result.outcome.state.value == "LANDED" and result.outcome.cause == "complete"
    return 0 if complete and result.log_incomplete is None and not result.outcome.errors else 1

