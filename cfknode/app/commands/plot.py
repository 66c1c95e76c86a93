"""``cfknode plot LOG [LOG ...]``: PNG plots of one flight, or of several overlaid to compare them; a fleet
log overlays its drones (``--drones`` chooses some)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cfknode.app.errors import UsageError

HELP = "plot flight logs: top view, altitude, error per axis, timing, model versions (PNG)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("logs", nargs="+", metavar="LOG", help="flight log (.mcap); several overlay to compare")
    p.add_argument("--out", help="directory for the PNGs (default: beside the first log, named after it)")
    p.add_argument("--dpi", type=int, default=None, help="pixels per inch (default 100: about 900 pixels wide)")
    p.add_argument("--drones", metavar="NAMES",
                   help="fleet log: plot only these drones, comma-separated (e.g. cf1,cf3); default all")


def default_out_dir(logs: list[str]) -> Path:
    first = Path(logs[0])
    suffix = "-plots" if len(logs) == 1 else f"-and-{len(logs) - 1}-more-plots"
    return first.with_name(first.stem + suffix)


def parse_drones(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",")]
    if not all(names):
        raise UsageError(f"--drones takes drone names separated by commas (e.g. cf1,cf3), got {text!r}")
    return names


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from cfknode.app.logs.format import LogError
    from cfknode.app.ui.plotting import DPI, plot_logs

    out = Path(args.out) if args.out else default_out_dir(args.logs)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} is a file; give a directory")
    if args.dpi is not None and not 20 <= args.dpi <= 600:
        raise UsageError(f"--dpi must be in 20..600, got {args.dpi}")
    drones = parse_drones(args.drones) if getattr(args, "drones", None) is not None else None
    try:
        report = plot_logs(args.logs, out, args.dpi or DPI, drones)
    except LogError as exc:
        raise UsageError(str(exc)) from None
    console = Console(soft_wrap=True, highlight=False)  # paths stay whole, to copy
    warned = set()
    for trace in report.traces:
        cut = f", [yellow]truncated at {trace.t_end:.2f} s[/]" if trace.truncated else ""
        console.print(f"{trace.path}: {trace.name}, {len(trace.t)} ticks{cut}")
        if trace.damage and trace.path not in warned:  # what was skipped, from when data is missing: once a log
            warned.add(trace.path)
            print(f"cfknode: warning: {trace.path}: {trace.damage}", file=sys.stderr)
    for name, path in report.files.items():
        console.print(f"  {name:<15} {path}")
    return 0
