"""The ``cfknode`` command line. Each subcommand lives in ``cfknode/app/commands/<name>.py``.

A command module provides ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. Bad input (a config key, a type, a missing file, a flag) ends
with one line on stderr naming what is wrong, and exit status 2.
"""

from __future__ import annotations

import os

# Before numpy loads: multithreaded BLAS on small products gave 16 ms latency spikes on
# this 2-core class of machine, far over a 2.5 ms tick; the flight path wants one thread.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import importlib  # noqa: E402
import sys  # noqa: E402
from typing import Sequence  # noqa: E402

from cfknode import __version__  # noqa: E402
from cfknode.app.cli_logging import command_logging  # noqa: E402
from cfknode.app.config import ConfigError  # noqa: E402
from cfknode.app.logs.format import LogError  # noqa: E402
from cfknode.app.errors import UsageError  # noqa: E402,F401 (re-exported)

COMMANDS: tuple[str, ...] = ("fly", "train", "model", "plot", "replay", "calibrate", "estop", "bench")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cfknode", description="KNODE-MPC-Online flight stack for Crazyflie 2.x")
    parser.add_argument("--version", action="version", version=f"cfknode {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        module = importlib.import_module(f"cfknode.app.commands.{name}")
        command = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(command)
        command.add_argument("-v", "--verbose", action="store_true",
                             help="show the libraries' log output (cflib, ...) as well as cfknode's, "
                                  "and every row of a flight's summary")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    module = importlib.import_module(f"cfknode.app.commands.{args.command}")
    with command_logging(args.verbose):
        try:
            return module.run(args)
        except (ConfigError, UsageError, LogError) as exc:
            print(f"cfknode: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt as exc:
            # Ctrl-C, or SIGTERM/SIGHUP before a flight could take off: 128 + the signal's number.
            signum = getattr(exc, "signum", 2)
            print("cfknode: interrupted" + (f" ({exc})" if signum != 2 else ""), file=sys.stderr)
            return 128 + signum


if __name__ == "__main__":
    sys.exit(main())
