"""A flight loop that never comes back after the radio stopped the motors for it: end the process.

The radio's TX thread stops the motors of a loop that stalls in flight (backends/stale_setpoint.py).
If the loop's thread then never returns (a hung call, a deadlock), nothing else would end the
process: it would sit there, motors off, until SIGKILL, and the log would lack its footer.
``stall_exit`` watches from a thread of its own: once a radio has stopped the motors for a stall
(``RadioStats.stale_stops``) and the loop has not ticked for ``grace_s`` since, it

1. writes an error on ``/events`` saying so (at the last tick's flight time),
2. hands each radio back and closes the flight log (footer written, everything recorded so far
   kept), each bounded in time: the stuck thread may hold the log's lock or the radio,
3. prints one line to stderr and leaves with ``os._exit(EXIT_STATUS)``: the loop's thread cannot
   be joined, and a normal exit would wait for it.

Only where a radio has a TX thread (wall-clock flights): in lockstep a blocked loop blocks the
simulator too, and nothing flies.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
from typing import Any, Callable, Iterator, Sequence

__all__ = ["EXIT_STATUS", "GRACE_S", "LoopProgress", "stall_exit"]

GRACE_S = 10.0  # wall seconds a loop gets to come back after its motors were stopped for it: far beyond a stall that ends
CLOSE_S = 2.0  # wall seconds each of the hand-back and the log close may take before we leave anyway
EXIT_STATUS = 1  # the flight did not end as planned (as any other cut-short flight)
_POLL_S = 0.1


class LoopProgress:
    """A tick observer: when the loop last ticked (monotonic) and at which flight time."""

    def __init__(self) -> None:
        self.wall = time.monotonic()
        self.t = 0.0

    def on_tick(self, info: Any) -> None:
        self.wall, self.t = time.monotonic(), float(info.t)


@contextlib.contextmanager
def stall_exit(radios: Sequence[Any], log: Any, progress: LoopProgress, grace_s: float = GRACE_S,
               leave: Callable[[int], None] = os._exit) -> Iterator[None]:
    """While the block runs, a thread watches for a loop stopped by its radio and gone for good (see
    the module docstring). ``log``: the flight log (``write``, ``close``, ``path``); ``leave``: how the
    process ends (``os._exit``; a test passes its own)."""
    done = threading.Event()
    watcher = threading.Thread(target=_watch, args=(radios, log, progress, grace_s, leave, done),
                               name="stall-exit", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        done.set()
        watcher.join(timeout=1.0)


def _stopped(radios: Sequence[Any]) -> bool:
    for radio in radios:
        with contextlib.suppress(Exception):  # a radio that cannot report has not stopped anything
            if radio.stats().stale_stops > 0:
                return True
    return False


def _watch(radios: Sequence[Any], log: Any, progress: LoopProgress, grace_s: float,
           leave: Callable[[int], None], done: threading.Event) -> None:
    stopped_at: float | None = None
    while not done.wait(_POLL_S):
        if stopped_at is None:
            if _stopped(radios):
                stopped_at = time.monotonic()
            continue
        now = time.monotonic()
        if now - max(stopped_at, progress.wall) < grace_s:
            continue
        if done.is_set():
            return  # the flight ended after all
        _leave(radios, log, progress, now - progress.wall, leave)
        return


def _bounded(action: Callable[[], Any], timeout: float) -> bool:
    """Run ``action`` on a thread of its own; whether it finished within ``timeout``."""
    worker = threading.Thread(target=_quiet, args=(action,), name="stall-exit-close", daemon=True)
    worker.start()
    worker.join(timeout)
    return not worker.is_alive()


def _quiet(action: Callable[[], Any]) -> None:
    try:
        action()
    except Exception:  # noqa: BLE001 - the process is leaving; what could not be closed is said below
        pass


def _leave(radios: Sequence[Any], log: Any, progress: LoopProgress, gone_s: float,
           leave: Callable[[int], None]) -> None:
    text = (f"the flight loop has not come back {gone_s:.1f} s after its last tick, and the radio has "
            "stopped the motors: the log is closed and the process exits")
    wrote = _bounded(lambda: log.write("/events", progress.t, {"level": "error", "text": text,
                                                                "source": "supervisor"}), CLOSE_S)
    for radio in radios:
        _bounded(radio.shutdown, CLOSE_S)
    closed = wrote and _bounded(log.close, CLOSE_S)
    where = f"log closed: {log.path}" if closed else f"the log could not be closed (kept as written): {log.path}"
    print(f"cfknode fly: the flight loop hung (no tick for {gone_s:.1f} s; motors stopped by the radio); "
          f"{where}; exiting with status {EXIT_STATUS}", file=sys.stderr)
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
    leave(EXIT_STATUS)
