"""Operator controls that reach a flight from outside the loop: stop signals and ``cfknode estop``.

- SIGINT (Ctrl-C), SIGTERM (``kill``, a service manager) and SIGHUP (the terminal closed):
  received by a relay thread (signal_relay.py), which only queues a request for the
  supervisor, so it acts at the next tick, and reaches the radio at once if the loop's thread
  is stuck. The previous handlers are put back when the flight ends. The first signal lands,
  the second stops the motors.
- The e-stop mailbox (``estop_mailbox``): the flight announces itself in a private directory
  and ``cfknode estop`` leaves a request file addressed to that one flight. A small task on
  the flight's event loop looks for it 20 times a second, between ticks (a file-system call
  releases the GIL, and getting it back can cost a tick tens of microseconds), hands it to
  the supervisor and deletes it, which is the acknowledgement the command waits for. Files,
  not a socket: nothing to serve, and a crash leaves only small files that no live flight reads.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
from typing import Iterator, Protocol

from cfknode.safety.estop_mailbox import EstopMailbox, describe_error, mailbox_dir
from cfknode.safety.signal_relay import relay_signals

__all__ = ["STOP_SIGNALS", "EstopMailbox", "estop_watch", "mailbox_dir", "stop_signal_handler"]

# The signals that end a flight the safe way (a landing, then a stop), never at once.
STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

# A flood guard: after this many distinct mailbox errors in one flight, the rest are not logged.
MAX_REPORTED_ERRORS = 20


class Interruptible(Protocol):
    def interrupt(self, signal_name: str) -> None: ...


class Stoppable(Protocol):
    def request_land(self, reason: str, cause: str) -> None: ...

    def request_stop(self, reason: str, cause: str) -> None: ...

    def note(self, level: str, text: str, source: str) -> None: ...


@contextlib.contextmanager
def stop_signal_handler(target: Interruptible, signals: tuple[signal.Signals, ...] = STOP_SIGNALS) -> Iterator[bool]:
    """Route ``signals`` to ``target.interrupt(name)`` while the block runs, from a relay thread
    (signal_relay.py), so a signal reaches ``target`` even while the loop's thread is blocked.

    Yields whether the handlers are installed (only the main thread may set signal handlers;
    elsewhere the signals keep their previous meaning). The previous handlers are restored on exit.
    """
    with relay_signals(target, signals) as installed:
        yield installed


@contextlib.contextmanager
def estop_watch(target: Stoppable, mailbox: EstopMailbox | None, period: float = 0.05) -> Iterator[None]:
    """While the block runs: the flight is announced in ``mailbox`` and a task on the running
    event loop hands each ``cfknode estop`` request to ``target``. Nothing without a mailbox.

    A mailbox opened by the caller (before take-off, where a refusal is still harmless) stays
    the caller's to close; one opened here is closed here.
    """
    if mailbox is None:
        yield
        return
    opened_here = not mailbox.is_open
    mailbox.open()
    task = asyncio.get_running_loop().create_task(_watch(target, mailbox, period))
    try:
        yield
    finally:
        task.cancel()
        if opened_here:
            mailbox.close()


async def _watch(target: Stoppable, mailbox: EstopMailbox, period: float) -> None:
    """Poll until cancelled. No error ends it: a dead watcher would leave the flight without
    its e-stop, so each distinct error is logged once as a safety event and polling goes on."""
    reported: set[str] = set()

    def report(level: str, text: str) -> None:
        if text in reported or len(reported) > MAX_REPORTED_ERRORS:
            return
        reported.add(text)
        if len(reported) > MAX_REPORTED_ERRORS:
            text = f"more than {MAX_REPORTED_ERRORS} distinct e-stop mailbox errors: no more are logged"
        target.note(level, f"e-stop mailbox: {text}", "estop")

    while True:
        await asyncio.sleep(period)
        try:
            request = mailbox.poll()
            if request is None:
                continue
            if request.note:
                report("warning", request.note)
            reason = f"cfknode estop --robot {mailbox.robot}" + (" --land" if request.action == "land" else "")
            if request.action == "land":
                target.request_land(reason, "estop_land")
            else:
                target.request_stop(reason, "estop_stop")
        except Exception as exc:  # noqa: BLE001 - see the docstring
            with contextlib.suppress(Exception):
                report("error", f"{describe_error(exc)}; still watching")
