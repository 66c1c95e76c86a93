"""``cfknode estop``: stop (or land) a running flight from another terminal.

The request goes through the e-stop mailbox (``cfknode.safety.estop_mailbox``) to one flight:
the only one running, or the one named by ``--robot`` (simulated flights are ``sim-<robot>``)
or ``--id``. The flight polls for it every few ticks, acts, and deletes it, which is the
acknowledgement this command waits for. Exit status 0 when the flight took it, 1 when no
flight did (none running, or it did not answer), 2 when the choice is ambiguous or the
mailbox directory is unsafe.
"""

from __future__ import annotations

import argparse
import sys

from cfknode.app.commands.fly import add_config_arguments, config_from_args

HELP = "stop the motors of a running flight (or land it with --land)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_config_arguments(p)
    p.add_argument("--robot", help="the flight's robot name (simulated flights: sim-<robot>); "
                                   "default: the only flight running")
    p.add_argument("--id", dest="flight_id", help="the flight's id (pid-hex, as listed when several fly)")
    p.add_argument("--all", dest="all_flights", action="store_true",
                   help="every running flight, e.g. every drone of a fleet (each drone is its own flight, sim-cf1 ...)")
    p.add_argument("--land", action="store_true", help="land instead of stopping the motors")
    p.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for the flight to take it")
    p.add_argument("--dir", help="e-stop mailbox directory (default: safety.estop_dir, else $XDG_RUNTIME_DIR/cfknode)")


def run(args: argparse.Namespace) -> int:
    from cfknode.app.commands.estop_all import report_skipped
    from cfknode.app.config import ConfigError
    from cfknode.safety.estop_mailbox import (
        MailboxError, NoFlight, check_dir, find_flight, mailbox_dir, request, scan_flights,
    )

    cfg = config_from_args(args, flags={"dir": "safety.estop_dir"})
    action = "land" if args.land else "stop"
    directory = mailbox_dir(cfg.safety.estop_dir)
    if getattr(args, "all_flights", False):
        from cfknode.app.commands.estop_all import estop_all

        return estop_all(directory, action, args.timeout)
    try:
        if directory.exists():
            check_dir(directory, create=False)  # before reading anything in it
        flight = find_flight(directory, args.robot, args.flight_id, scan=report_skipped(scan_flights(directory)))
    except NoFlight as exc:
        print(f"cfknode estop: {exc}", file=sys.stderr)
        return 1
    except MailboxError as exc:  # several flights match, or an unsafe directory
        raise ConfigError(str(exc)) from None
    try:
        taken = request(flight, action, timeout=args.timeout)
    except MailboxError as exc:  # e.g. something that is not a file sits at the request path
        print(f"cfknode estop: the {action} request did not reach the flight of {flight.robot!r}: {exc}",
              file=sys.stderr)
        return 1
    if taken:
        print(f"cfknode estop: {action} taken by the flight of {flight.robot!r} (pid {flight.pid}, id {flight.id})")
        return 0
    print(f"cfknode estop: the flight of {flight.robot!r} (pid {flight.pid}, id {flight.id}) did not take the "
          f"{action} request within {args.timeout:g} s", file=sys.stderr)
    return 1
