"""``cfknode estop``: stop (or land) a running flight from another terminal.

The request goes through the e-stop mailbox (``cfknode.safety.operator``): the flight of that
robot polls for it every few ticks, acts, and deletes it, which is the acknowledgement this
command waits for. Exit status 0 when the flight took it, 1 when no flight did.
"""

from __future__ import annotations

import argparse
import sys

from cfknode.commands.fly import add_config_arguments, config_from_args

HELP = "stop the motors of a running flight (or land it with --land)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_config_arguments(p)
    p.add_argument("--robot", help="the flight's robot name (default: the config's hardware.robot)")
    p.add_argument("--land", action="store_true", help="land instead of stopping the motors")
    p.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for the flight to take it")
    p.add_argument("--dir", help="e-stop mailbox directory (default: safety.estop_dir, else $XDG_RUNTIME_DIR/cfknode)")


def run(args: argparse.Namespace) -> int:
    from cfknode.safety.operator import EstopMailbox, mailbox_dir

    cfg = config_from_args(args, flags={"robot": "hardware.robot", "dir": "safety.estop_dir"})
    robot = cfg.hardware.robot
    mailbox = EstopMailbox(mailbox_dir(cfg.safety.estop_dir), robot)
    action = "land" if args.land else "stop"
    pid = mailbox.flight_pid()
    if pid is None:
        print(f"cfknode estop: no flight of {robot!r} is running (mailbox {mailbox.directory})", file=sys.stderr)
        return 1
    if mailbox.request(action, timeout=args.timeout):
        print(f"cfknode estop: {action} taken by the flight of {robot!r} (pid {pid})")
        return 0
    print(f"cfknode estop: the flight of {robot!r} (pid {pid}) did not take the {action} request "
          f"within {args.timeout:g} s", file=sys.stderr)
    return 1
