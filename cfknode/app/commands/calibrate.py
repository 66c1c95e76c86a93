"""``cfknode calibrate``: a short hover that estimates the hover thrust and mass, written to the robots file."""

from __future__ import annotations

import argparse
import sys

from cfknode.app.errors import UsageError
from cfknode.app.commands.fly import FLAGS, add_config_arguments, add_hardware_arguments, config_from_args

HELP = "hover briefly and write the robot's hover thrust command and mass to the robots file"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_config_arguments(p)
    add_hardware_arguments(p)
    p.add_argument("--height", type=float, default=0.5, help="hover height [m]")
    p.add_argument("--duration", type=float, default=4.0, help="seconds of steady hover to average")
    p.add_argument("--no-write", action="store_true", help="estimate only; leave the robots file as it is")
    p.add_argument("--log-dir", dest="log_dir", help="directory for the calibration flight's log")


def run(args: argparse.Namespace) -> int:
    flags = {k: v for k, v in FLAGS.items() if k in ("backend", "robot", "robots_file", "mocap", "mocap_host", "log_dir")}
    cfg = config_from_args(args, flags)
    if len(args.robot_names) > 1:
        raise UsageError("calibrate flies one robot: --robot NAME (or --robots NAME)")
    from cfknode.app.backends.calibrate import CalibrationError, calibrate
    from cfknode.app.mission import MissionError

    try:
        result = calibrate(cfg, write=not args.no_write, height=args.height, hover_s=args.duration)
    except (CalibrationError, MissionError) as exc:
        print(f"cfknode: error: {exc}", file=sys.stderr)
        return 1
    print(result.message)
    return 0
