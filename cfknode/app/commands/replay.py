"""``cfknode replay LOG``: run a controller offline on a flight's logged states and compare its commands."""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

from cfknode.app.errors import UsageError
from cfknode.app.config import parse_override

HELP = "re-run the controller (and a KNODE model) on a flight log's states and compare the commands"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", metavar="LOG", help="flight log (.mcap)")
    p.add_argument("--model", help="KNODE model file: the MPC predicts with it (default: as the log's config)")
    p.add_argument("--solver", choices=["rti", "ipopt"], help="override controller.solver")
    p.add_argument("--qp-solver", dest="qp_solver", choices=["qrqp", "osqp"], help="override controller.qp_solver")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a key of the flight's config (e.g. controller.q_position=[80,80,80]; every key: "
                        "docs/configuration.md)")
    p.add_argument("--csv", help="write logged and replayed commands per tick to this CSV file")
    p.add_argument("--png", help="plot logged and replayed commands to this PNG file")
    p.add_argument("--json", action="store_true", help="print the comparison as one JSON object")
    p.add_argument("--drone", metavar="NAME", help="fleet log: replay this drone (e.g. cf2)")


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from cfknode.app.logs.fleet_log import drone_log, fleet_drones
    from cfknode.app.logs.reader import LogError, read_log, require_messages
    from cfknode.app.replay import COMMAND_FIELDS, ReplayError, load_residual_model, logged_config, plot_replay, \
        replay_log, write_csv

    overrides = dict(parse_override(item) for item in args.set)
    if args.solver:
        overrides["controller.solver"] = args.solver
    if args.qp_solver:
        overrides["controller.qp_solver"] = args.qp_solver
    try:
        log = read_log(args.log)
        names = fleet_drones(log)
        if names:
            log = drone_log(log, _chosen_drone(args, names))
        elif args.drone is not None:
            raise UsageError(f"{args.log}: --drone: this log is a single drone's flight, not a fleet's")
        require_messages(log, ("/state", "/command"))
        cfg, dropped = logged_config(log, overrides)
        trajectory = None
        if names:
            cfg, trajectory = _fleet_drone(cfg, names.index(args.drone))
        model, model_name = load_residual_model(args.model) if args.model else (None, None)
        result = replay_log(log, cfg, model, model_name, trajectory)
    except (LogError, ReplayError) as exc:
        raise UsageError(str(exc)) from None
    if args.csv:
        write_csv(result, args.csv)
    if args.png:
        plot_replay(result, args.png, title=f"replay of {log.path.name}: {result.controller}"
                    + (f" + {model_name}" if model_name else ""))

    rms, worst = result.rms(), result.max_abs()
    if log.note:  # what the reader skipped, and from when data is missing
        print(f"cfknode: warning: {log.path}: {log.note}", file=sys.stderr)
    if args.json:
        print(json.dumps({
            "log": str(log.path), "ticks": result.ticks, "skipped": dict(result.skipped),
            "controller": result.controller, "model": model_name, "source_changes": result.source_changes(),
            "reference_mismatch_m": result.reference_mismatch_m, "notes": list(result.notes),
            "rms": {k: _finite(v) for k, v in rms.items()}, "max": {k: _finite(v) for k, v in worst.items()},
            "log_damage": log.damage.to_dict(),
        }))
        return 0
    console = Console()
    skipped = ", ".join(f"{n} {k}" for k, n in sorted(result.skipped.items())) or "none"
    console.print(f"[bold]replay[/] {log.path.name}{' (truncated)' if log.truncated else ''}: "
                  f"{result.ticks} controller ticks with {result.controller}"
                  + (f" + {model_name}" if model_name else "") + f"; not replayed: {skipped}")
    table = Table(title="replayed minus logged command", header_style="bold")
    for column in ("command", "unit", "RMS difference", "max |difference|", "RMS of logged"):
        table.add_column(column, justify="left" if column in ("command", "unit") else "right")
    for i, (name, unit) in enumerate(COMMAND_FIELDS):
        scale = math.sqrt(float((result.logged[:, i] ** 2).mean()))
        table.add_row(name, unit, f"{rms[name]:.3g}", f"{worst[name]:.3g}", f"{scale:.3g}")
    console.print(table)
    changes = result.source_changes()
    if changes:
        console.print(f"[yellow]{changes} tick(s) flew another controller in replay than in flight[/]")
    for note in result.notes:
        console.print(f"[yellow]note:[/] {note}")
    if dropped:
        print(f"note: config keys of the log unknown to this version, ignored: {', '.join(dropped)}", file=sys.stderr)
    for what, path in (("CSV", args.csv), ("PNG", args.png)):
        if path:
            console.print(f"wrote {what} {path}")
    return 0


def _chosen_drone(args: argparse.Namespace, names: list[str]) -> str:
    if args.drone is None:
        raise UsageError(f"{args.log} is a fleet log: choose a drone with --drone ({', '.join(names)})")
    if args.drone not in names:
        raise UsageError(f"{args.log}: no drone {args.drone} in this fleet log; it has {', '.join(names)}")
    return str(args.drone)


def _fleet_drone(cfg: Any, index: int) -> tuple[Any, Any]:
    """Drone ``index``'s own config (start, seed) and reference, rebuilt from the fleet's config as it flew."""
    from cfknode.app.config import ConfigError
    from cfknode.app.fleet.flight import drone_configs
    from cfknode.app.replay import ReplayError

    try:
        _, configs, refs = drone_configs(cfg)
    except ConfigError as exc:
        raise ReplayError(f"the fleet's drones cannot be rebuilt from the logged config: {exc}") from None
    return configs[index], refs[index].inner


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None
