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
  That task does not run while the loop's thread is stuck, so a thread of its own watches it:
  once the task is ``STALLED_AFTER_S`` late with its poll, the thread polls instead
  and hands each request on the same way. The supervisor passes a stop on to its radio at once
  (``request_stop``), whose TX thread stops the motors while the loop is stalled
  (cfknode/app/backends/stale_setpoint.py); a landing is the radio's level, descending hold,
  which it flies anyway then. The thread's own errors are kept for the task to log once the
  loop is back (only the loop's thread writes the log).
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
import threading
import time
from typing import Callable, Iterator, Protocol

from cfknode.safety.estop_mailbox import EstopMailbox, describe_error, mailbox_dir
from cfknode.safety.signal_relay import relay_signals

__all__ = ["STOP_SIGNALS", "EstopMailbox", "estop_watch", "mailbox_dir", "stop_signal_handler"]

# The signals that end a flight the safe way (a landing, then a stop), never at once.
STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

# A flood guard: after this many distinct mailbox errors in one flight, the rest are not logged.
MAX_REPORTED_ERRORS = 20
# The event loop's poll this late (this many periods, at least STALLED_AFTER_S): its thread is
# stuck, the watch thread polls. Not sooner: a slow tick on a loaded machine is no stall, and the
# radio's own stop comes only after its stop_after_s (1 s by default).
STALLED_AFTER_POLLS = 4
STALLED_AFTER_S = 0.25


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
    poller = _Poller(target, mailbox)
    task = asyncio.get_running_loop().create_task(_watch(poller, period))
    done = threading.Event()
    watcher = threading.Thread(target=_watch_stalled, args=(poller, period, done), name="estop-stall-watch",
                               daemon=True)
    watcher.start()
    try:
        yield
    finally:
        done.set()
        task.cancel()
        watcher.join(timeout=1.0)
        _report_deferred(poller)  # on the loop's thread again
        if opened_here:
            mailbox.close()


class _Poller:
    """One mailbox, polled from the event loop or (while that is stuck) from the watch thread,
    never both at once; ``last_poll`` is when the event loop last did (monotonic)."""

    def __init__(self, target: Stoppable, mailbox: EstopMailbox) -> None:
        self.target, self.mailbox = target, mailbox
        self.lock = threading.Lock()
        self.last_poll = time.monotonic()
        self.reported: set[str] = set()
        self.deferred: list[tuple[str, str]] = []  # (level, text) found by the watch thread, not logged yet

    def report(self, level: str, text: str) -> None:
        """Log a distinct mailbox problem once (the event loop's thread only)."""
        if text in self.reported or len(self.reported) > MAX_REPORTED_ERRORS:
            return
        self.reported.add(text)
        if len(self.reported) > MAX_REPORTED_ERRORS:
            text = f"more than {MAX_REPORTED_ERRORS} distinct e-stop mailbox errors: no more are logged"
        self.target.note(level, f"e-stop mailbox: {text}", "estop")

    def poll(self, report: Callable[[str, str], None]) -> None:
        """Take one request, if any, and hand it to the target. No error escapes: a dead watcher
        would leave the flight without its e-stop, so each goes to ``report`` and polling goes on."""
        with self.lock:
            try:
                request = self.mailbox.poll()
                if request is None:
                    return
                if request.note:
                    report("warning", request.note)
                reason = f"cfknode estop --robot {self.mailbox.robot}" + (" --land" if request.action == "land" else "")
                if request.action == "land":
                    self.target.request_land(reason, "estop_land")
                else:
                    self.target.request_stop(reason, "estop_stop")
            except Exception as exc:  # noqa: BLE001 - see the docstring
                with contextlib.suppress(Exception):
                    report("error", f"{describe_error(exc)}; still watching")


async def _watch(poller: _Poller, period: float) -> None:
    """Poll until cancelled, and log what the watch thread found while the loop was stuck."""
    while True:
        await asyncio.sleep(period)
        poller.last_poll = time.monotonic()
        _report_deferred(poller)
        poller.poll(poller.report)


def _report_deferred(poller: _Poller) -> None:
    while poller.deferred:
        with contextlib.suppress(Exception):
            poller.report(*poller.deferred.pop(0))


def _watch_stalled(poller: _Poller, period: float, done: threading.Event) -> None:
    """The watch thread: poll whenever the event loop's own poll is late enough to be a stall."""
    late = max(STALLED_AFTER_POLLS * period, STALLED_AFTER_S)
    while not done.wait(period):
        if time.monotonic() - poller.last_poll > late:
            poller.poll(lambda level, text: poller.deferred.append((level, text)))
