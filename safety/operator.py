"""Operator controls that reach a flight from outside the loop: Ctrl-C and ``cfknode estop``.

- SIGINT: installed with ``loop.add_signal_handler`` on the flight's own event loop, so the
  handler runs between ticks as an ordinary callback (never inside a tick), and the previous
  handler is put back when the flight ends. First Ctrl-C lands, the second stops the motors.
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
from typing import Any, Callable, Iterator, Protocol

from cfknode.safety.estop_mailbox import EstopMailbox, describe_error, mailbox_dir

__all__ = ["EstopMailbox", "estop_watch", "mailbox_dir", "sigint_handler"]

# A flood guard: after this many distinct mailbox errors in one flight, the rest are not logged.
MAX_REPORTED_ERRORS = 20


class Interruptible(Protocol):
    def interrupt(self) -> None: ...


class Stoppable(Protocol):
    def request_land(self, reason: str, cause: str) -> None: ...

    def request_stop(self, reason: str, cause: str) -> None: ...

    def note(self, level: str, text: str, source: str) -> None: ...


@contextlib.contextmanager
def sigint_handler(target: Interruptible) -> Iterator[bool]:
    """Route SIGINT to ``target.interrupt()`` on the running event loop while the block runs.

    Yields whether the handler is installed (only the main thread may set signal handlers;
    elsewhere Ctrl-C keeps its previous meaning). The previous handler is restored on exit.
    """
    loop = asyncio.get_running_loop()
    previous: Callable[..., Any] | int | None = signal.getsignal(signal.SIGINT)
    try:
        loop.add_signal_handler(signal.SIGINT, target.interrupt)
    except (RuntimeError, ValueError, NotImplementedError):
        yield False
        return
    try:
        yield True
    finally:
        loop.remove_signal_handler(signal.SIGINT)
        if previous is not None:
            signal.signal(signal.SIGINT, previous)


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
