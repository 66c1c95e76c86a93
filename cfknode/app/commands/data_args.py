"""The data options ``cfknode train`` and ``cfknode model check`` share, and reading the data they name.

cfknode's own flight logs (``--log``, MCAP) and other people's tables (``--data``, CSV or Parquet
in the schema of docs/data.md) both become training segments; each file, or each manoeuvre of a
table with a ``manoeuvre`` column, is a group that a held-out split keeps whole.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from dataclasses import replace

from typing import TYPE_CHECKING

from cfknode.app.config import Config, ConfigError

if TYPE_CHECKING:  # torch sits under these: the command line imports them only when data is read
    from cfknode.app.data.prepare import Preparation
    from cfknode.models.training import Dataset, Segment


def add_data_arguments(p: argparse.ArgumentParser, logs_required: bool = False) -> None:
    p.add_argument("--log", action="append", default=[], metavar="FLIGHT_LOG", help="cfknode flight log (repeatable)")
    p.add_argument("--data", action="append", default=[], metavar="TABLE",
                   help="CSV or Parquet flight table in the schema of docs/data.md, or a ROS 2 bag of "
                        "Crazyswarm2's topics (its folder, .mcap or .db3) (repeatable)")
    p.add_argument("--robot", metavar="NAME", help="the robot whose topics a ROS 2 bag is read for "
                   "(/NAME/pose, /NAME/cmd_vel_legacy; default hardware.robot)")
    p.add_argument("--columns", metavar="NAME=COLUMN,...", help="map the table's column names onto the schema's")
    p.add_argument("--thrust-coefficient", dest="thrust_coefficient", type=float, metavar="N_PER_RAD2_S2",
                   help="thrust per motor speed squared, for tables with motor speeds m1..m4 (rad/s)")
    p.add_argument("--align", default="auto", metavar="auto|none|SECONDS",
                   help="delay of the input against the state: estimated (auto), none, or given")
    p.add_argument("--every", type=int, default=1, metavar="N", help="keep every N-th sample of a table")
    p.add_argument("--split", choices=["auto", "group", "tail"], default="auto",
                   help="held-out data: whole manoeuvres or files (group), the last part of each run (tail), "
                        "or group when there are at least two, else tail (auto)")


def read_segments(args: argparse.Namespace, cfg: Config,
                  say: Callable[[str], None] = lambda line: print(f"cfknode: {line}", file=sys.stderr),
                  ) -> tuple[list[Segment], list[Preparation]]:
    """Every segment from ``--log`` and ``--data``, and one preparation report per table."""
    from cfknode.app.data.prepare import TableOptions, prepare
    from cfknode.app.data.rosbag import is_bag, read_bag
    from cfknode.app.data.tables import parse_column_map, read_table
    from cfknode.app.logs.training_data import segments_from_logs

    if not args.log and not args.data:
        raise ConfigError("give flight data: --log FLIGHT_LOG (cfknode's) or --data TABLE (CSV, Parquet)")
    if args.every < 1:
        raise ConfigError(f"--every must be at least 1, got {args.every}")
    segments = segments_from_logs(args.log, lambda line: say(f"warning: {line}")) if args.log else []
    columns = parse_column_map(args.columns)
    v = cfg.vehicle
    opts = TableOptions(mass=v.mass, gravity=v.gravity, newton_per_cmd=v.newton_per_cmd,
                        thrust_coefficient=args.thrust_coefficient, align=args.align, every=args.every)
    preps = []
    for path in args.data:
        table = (read_bag(path, args.robot or cfg.hardware.robot) if is_bag(path) else read_table(path, columns))
        found, prep = prepare(table, str(path), opts)
        if not found:
            raise ConfigError(f"{path}: no run of at least 20 clean samples to train on ({prep.line()})")
        say(prep.line())
        segments.extend(found)
        preps.append(prep)
    if any(x > 0.0 for x in cfg.training.command_lag_s):
        from cfknode.flight.learning.command_lag import lagged_commands

        segments = [replace(s, u=lagged_commands(s.t, s.u, cfg.training.command_lag_s)) for s in segments]
    return segments, preps


def dataset_for(segments: Sequence[Segment], cfg: Config, split: str) -> tuple[Dataset, tuple[str, ...]]:
    """The training set and its held-out part by ``split``, and the held-out groups (empty for tail)."""
    from cfknode.app.data.check import split_by_group, split_dataset
    from cfknode.models.training import make_dataset

    groups = {s.source for s in segments}
    try:
        if split == "group" or (split == "auto" and len(groups) >= 2):
            train, held = split_by_group(segments)
            held_out = tuple(dict.fromkeys(s.source for s in held))
            return split_dataset(train, held, cfg.training.velocity_filter_hz), held_out
        return make_dataset(segments, cfg.training.velocity_filter_hz, cfg.training.validation_fraction), ()
    except ValueError as exc:
        raise ConfigError(f"cannot train on this data: {exc}") from None
