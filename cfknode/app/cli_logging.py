"""Where log records go while a command runs: cfknode's own warnings on stderr, the rest on request.

Libraries log their failures with tracebacks (cflib logs "Couldn't load link driver" with the
whole stack when no Crazyradio is plugged in) and Python prints such records on stderr when
nothing else handles them, ahead of cfknode's one-line error. So a command installs this
handler on the root logger: without ``--verbose`` it shows only cfknode's own warnings and
counts what it holds back; with ``--verbose`` it shows every record from INFO up.
"""

from __future__ import annotations

import contextlib
import logging
import sys
from typing import Iterator

OWN_LOGGER = "cfknode"


class CommandLogHandler(logging.Handler):
    """Writes to the current ``sys.stderr`` (looked up per record, so redirection works)."""

    def __init__(self, verbose: bool) -> None:
        super().__init__(logging.INFO if verbose else logging.WARNING)
        self.verbose = verbose
        self.held_back = 0  # records not shown (library records without --verbose)
        self.setFormatter(logging.Formatter("%(name)s: %(levelname)s: %(message)s"))

    def emit(self, record: logging.LogRecord) -> None:
        own = record.name == OWN_LOGGER or record.name.startswith(OWN_LOGGER + ".")
        if not (own or self.verbose):
            self.held_back += 1
            return
        try:
            sys.stderr.write(self.format(record) + "\n")
        except Exception:  # noqa: BLE001 (logging must never end the command)
            self.handleError(record)


@contextlib.contextmanager
def command_logging(verbose: bool) -> Iterator[CommandLogHandler]:
    """Install the handler on the root logger for the span of one command, then remove it."""
    root = logging.getLogger()
    handler = CommandLogHandler(verbose)
    old_level = root.level
    root.addHandler(handler)
    if verbose and root.getEffectiveLevel() > logging.INFO:
        root.setLevel(logging.INFO)
    try:
        yield handler
    finally:
        root.removeHandler(handler)
        root.setLevel(old_level)
